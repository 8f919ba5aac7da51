"""A training run's folder as the report reads it: its file names (`RUN_FILES`) and `load_run`,
which reads what it can and names every missing or unreadable file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, NamedTuple

from evojax_motion.errors import UserError

# The run folder's files (train.py writes them; names repeated here so that reading a report needs
# no JAX import before it is needed).
CONFIG_FILE, METRICS_FILE, SUMMARY_FILE = "config.yaml", "metrics.jsonl", "summary.json"
DB_INITIAL, DB_GEN1, DB_FINAL = "db_initial.npz", "db_gen1.npz", "db_final.npz"
RUN_FILES = (CONFIG_FILE, METRICS_FILE, DB_INITIAL, DB_GEN1, DB_FINAL)
# optional: written by `benchmarks/catch_success.py --train-dir RUN` (catches in physics)
CATCH_FILE = "catch_success.json"


class RunData(NamedTuple):
    """What could be read from a run folder; None where a file is missing or unreadable."""

    run_dir: Path
    config: Any  # evojax_motion.settings.Config
    metrics: list[dict] | None
    summary: dict | None
    db_initial: Any  # (Database, DatabaseMeta)
    db_gen1: Any
    db_final: Any
    problems: dict[str, str]  # file name -> what is wrong
    catch: dict | None = None  # CATCH_FILE, where the catch benchmark ran on this run


def _read_catch(path: Path) -> dict:
    """CATCH_FILE: per database, ``caught`` of ``reachable`` throws and the motions' eq. 5 cost."""
    try:
        result = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: not JSON ({e.msg})") from None
    dbs = result.get("databases") if isinstance(result, dict) else None
    keys = ("caught", "reachable", "cost")
    if (
        not isinstance(dbs, dict)
        or not dbs
        or not all(isinstance(r, dict) and all(k in r for k in keys) for r in dbs.values())
    ):
        raise UserError(
            f"{path}: expected {{'databases': {{name: {{{', '.join(keys)}, ...}}}}}} "
            "as benchmarks/catch_success.py writes it"
        )
    return result


def _read_metrics(path: Path) -> list[dict]:
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as e:
            raise UserError(f"{path}: line {n}: not JSON ({e.msg})") from None
        if not isinstance(row, dict) or "generation" not in row:
            raise UserError(f"{path}: line {n}: expected an object with a 'generation' field")
        rows.append(row)
    if not rows:
        raise UserError(f"{path}: holds no generation yet")
    return rows


def load_run(run_dir: str | Path) -> RunData:
    """Read everything a report can use from ``run_dir``; missing or unreadable files become
    ``problems``. Raises `UserError` when ``run_dir`` does not exist or holds none of the run's
    files (`RUN_FILES`)."""
    from evojax_motion.motion.database import load_database
    from evojax_motion.settings import load_config

    run = Path(run_dir)
    if not run.is_dir():
        what = "is a file, not a run directory" if run.exists() else "no such directory"
        raise UserError(f"{run}: {what}")
    if not any((run / name).is_file() for name in RUN_FILES):
        raise UserError(
            f"{run}: holds no training run (none of {', '.join(RUN_FILES)}); "
            "expected the --out folder of `evojax-motion train`"
        )
    problems: dict[str, str] = {}

    def attempt(name, reader):
        path = run / name
        if not path.is_file():
            problems[name] = f"{path}: missing"
            return None
        try:
            return reader(path)
        except UserError as e:
            problems[name] = str(e)
        except (OSError, ValueError) as e:
            problems[name] = f"{path}: unreadable ({e})"
        return None

    summary = None
    if (run / SUMMARY_FILE).is_file():  # optional: written at the end of a run
        try:
            summary = json.loads((run / SUMMARY_FILE).read_text())
        except (OSError, json.JSONDecodeError):
            summary = None
    catch = attempt(CATCH_FILE, _read_catch) if (run / CATCH_FILE).is_file() else None
    return RunData(
        run_dir=run,
        config=attempt(CONFIG_FILE, load_config),
        metrics=attempt(METRICS_FILE, _read_metrics),
        summary=summary,
        db_initial=attempt(DB_INITIAL, load_database),
        db_gen1=attempt(DB_GEN1, load_database),
        db_final=attempt(DB_FINAL, load_database),
        problems=problems,
        catch=catch,
    )
