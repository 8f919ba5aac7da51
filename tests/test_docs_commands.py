"""The shell commands of README.md and docs/*.md run as written.

A command is a line of a fenced block marked ``bash``, ``sh``, ``shell`` or ``console``, or of an
unmarked block when it starts with ``evojax-motion``, ``python`` or ``make`` (also as
``.venv/bin/...``); comments and line continuations are resolved as bash would. Each one is

- run as written, in one temporary folder that holds the repository's ``configs/``, the shipped
  sample (``evojax_motion/data/``) and a copy of ``notebooks/``, in the order of the documents
  (README.md first; a command written in several places runs once), after the commands whose
  files it reads (a path another command writes with ``--out``, or a config's ``demos_file``);
- or run with the changes of `SUBSTITUTED` (smaller sizes, the reason given);
- or not run, for the reason given in `NOT_RUN`.

A command that fails, or one that is in neither table and cannot be run, fails the test naming
its file and line; an entry of a table that no document holds any more fails it too. Commands
that train (``train``, ``make demo``), make a report or read a trained run are marked slow; one
tiny training run (``make demo``'s, on configs/tiny.yaml) serves every command on ``runs/demo``.
"""

from __future__ import annotations

import glob
import re
import shlex
import shutil
import subprocess
import sys
from functools import cache
from pathlib import Path
from typing import NamedTuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = (ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")))
SHELL_LANGS = ("bash", "sh", "shell", "console")
PLAIN_BLOCK_COMMANDS = ("evojax-motion", "python", "make")
VENV_BIN = ".venv/bin/"
TIMEOUT_S = 600  # one command; the slowest (the tiny training run) takes ~2 min on 2 busy cores
SLOW_SUBCOMMANDS = ("train", "report")  # end-to-end training, or JAX compiles + rendering

IMPORT = (
    "evojax-motion import --format vicon-csv --robot mahru_arm "
    "--out runs/reach_real_demos.npz evojax_motion/data/ue_adl_sample"
)
TRAIN_REACH = "evojax-motion train configs/reach_real.yaml --out runs/reach_real"
SHARDED = "python benchmarks/sharded_generations.py"

# doc command -> (the command run instead, why). Sizes only: the same subcommand and files.
SUBSTITUTED: dict[str, tuple[str, str]] = {
    "make demo": (
        "evojax-motion train configs/tiny.yaml --out runs/demo",
        "the training command of the Makefile's demo target, on configs/tiny.yaml instead of "
        "configs/demo_small.yaml (minutes on 2 CPU cores) and without creating .venv (the tests "
        "run in it); the run every command on runs/demo reads",
    ),
    IMPORT: (
        f"{IMPORT} --samples 32",
        "T = 32 samples instead of 100, so that the training on it compiles quickly (the "
        "shapes of tests/demonstrations/test_import.py's training)",
    ),
    TRAIN_REACH: (
        f"{TRAIN_REACH} --set evolution.conditions=16 --set evolution.generations=1",
        "one generation of 16 conditions instead of 10 of 40 (~30 s each on 2 CPU cores): the "
        "sizes of tests/demonstrations/test_import.py's training, whose programs the test run's "
        "XLA cache then holds",
    ),
}

# doc command -> why it is not run
NOT_RUN: dict[str, str] = {
    "make test": "the whole test suite with lint, this test included",
    ".venv/bin/evojax-motion train configs/catch_ball.yaml --out runs/paper": (
        "the paper's scale (300 conditions, T = 100; minutes on 2 CPU cores); the same "
        "command runs on configs/tiny.yaml for `make demo`, and tests/settings/test_config.py "
        "loads configs/catch_ball.yaml"
    ),
    "evojax-motion report RUN_DIR [--out DIR] [--condition C] [--joint NAME]": (
        "a usage synopsis (placeholders); README's `evojax-motion report runs/demo` runs it"
    ),
    **dict.fromkeys(
        (
            f"JAX_COORDINATOR_ADDRESS=127.0.0.1:12345 EVOJAX_NUM_PROCESSES=2 EVOJAX_PROCESS_ID={i} "
            f"CUDA_VISIBLE_DEVICES={i} evojax-motion train configs/catch_ball.yaml "
            "--out runs/catch --distributed &"
            for i in (0, 1)
        ),
        "one process per GPU on a host with 2 GPUs, at the paper's scale; tests/run/"
        "test_distributed.py launches train --distributed as 2 processes of 2 CPU devices",
    ),
    "srun --nodes=2 --ntasks-per-node=8 --gpus-per-node=8 evojax-motion train "
    "configs/catch_ball.yaml --out runs/catch --distributed": "a SLURM launch on 2 GPU hosts",
    "JAX_COORDINATOR_ADDRESS=host0:12345 EVOJAX_NUM_PROCESSES=16 EVOJAX_PROCESS_ID=8 "
    "CUDA_VISIBLE_DEVICES=0 evojax-motion train configs/catch_ball.yaml --out runs/catch "
    "--distributed": "one process of a 16-GPU run on 2 hosts",
    f"{SHARDED} --sweep-conditions 100000 --devices 1,2,4 --unsharded --generations 3 "
    "--tag h200x4": "a benchmark for several GPUs (minutes per point)",
    f"{SHARDED} --config configs/demo_small.yaml --generations 2 --sweep-conditions 10000 "
    "--devices 1,2 --tag h200x2_small": "a benchmark for several GPUs (minutes per point)",
}


class DocCommand(NamedTuple):
    """A command of the documents: ``text`` (its words joined by single spaces), ``tokens`` (as
    bash splits them) and where it is written (``["README.md:54", ...]``)."""

    text: str
    tokens: tuple[str, ...]
    where: tuple[str, ...]


_FENCE = re.compile(r"^\s*```\s*([\w+-]*)")


def _words(line: str, lang: str) -> tuple[str, ...] | None:
    """The words of a command line, or None when the line is no command of the block."""
    if lang == "console":
        if not line.lstrip().startswith("$ "):
            return None  # a console block's output
        line = line.lstrip()[2:]
    try:
        words = tuple(shlex.split(line, comments=True))
    except ValueError:  # unbalanced quotes: no command, unless the block says it is shell
        words = (line.strip(),) if lang in SHELL_LANGS else ()
    if not words:
        return None
    if lang not in SHELL_LANGS and words[0].removeprefix(VENV_BIN) not in PLAIN_BLOCK_COMMANDS:
        return None
    return words


def extract_commands(path: Path) -> list[tuple[tuple[str, ...], str]]:
    """``[(words, "FILE:LINE")]`` of the shell commands in ``path``'s fenced code blocks."""
    lines = path.read_text().splitlines()
    name = path.relative_to(ROOT).as_posix()
    found = []
    lang: str | None = None  # None: outside a block
    i = 0
    while i < len(lines):
        fence = _FENCE.match(lines[i])
        if fence:
            lang = fence.group(1).lower() if lang is None else None
        elif lang is not None and (lang in SHELL_LANGS or lang == ""):
            start, text = i, lines[i]
            while text.endswith("\\") and i + 1 < len(lines):  # bash drops backslash-newline
                i += 1
                text = text[:-1] + lines[i]
            words = _words(text, lang)
            if words:
                found.append((words, f"{name}:{start + 1}"))
        i += 1
    return found


@cache
def doc_commands() -> tuple[DocCommand, ...]:
    """Every command of `DOCS`, once each, in the documents' order."""
    where: dict[str, list[str]] = {}
    tokens: dict[str, tuple[str, ...]] = {}
    for doc in DOCS:
        for words, loc in extract_commands(doc):
            text = " ".join(words)
            tokens.setdefault(text, words)
            where.setdefault(text, []).append(loc)
    return tuple(DocCommand(t, tokens[t], tuple(w)) for t, w in where.items())


def _option(tokens, name: str) -> str | None:
    return tokens[tokens.index(name) + 1] if name in tokens[:-1] else None


def _subcommand(tokens) -> str | None:
    return tokens[1] if tokens[0].removeprefix(VENV_BIN) == "evojax-motion" else None


def run_tokens(cmd: DocCommand) -> tuple[str, ...]:
    """The words actually run for ``cmd`` (`SUBSTITUTED`'s, else its own)."""
    return tuple(shlex.split(SUBSTITUTED[cmd.text][0])) if cmd.text in SUBSTITUTED else cmd.tokens


def reads(tokens) -> list[str]:
    """Paths of generated files a command reads: ``--db``, ``report``'s run folder, a training
    config's ``demos_file``."""
    paths = [p for p in (_option(tokens, "--db"),) if p]
    sub = _subcommand(tokens)
    if sub == "report":
        paths.append(tokens[2])
    if sub == "train" and len(tokens) > 2:
        from evojax_motion.errors import UserError
        from evojax_motion.settings import load_config

        try:
            demos = load_config(ROOT / tokens[2]).demos_file
        except UserError:  # a config that does not load: the command fails when it runs
            demos = None
        if demos:
            paths.append(demos)
    return paths


def writes(tokens) -> str | None:
    out = _option(tokens, "--out")
    return out.rstrip("/") if out else None


def producers(cmd: DocCommand) -> tuple[list[DocCommand], list[str]]:
    """``(commands, missing)``: the commands before ``cmd`` that write what it reads, and the
    paths it reads that no command before it writes."""
    earlier: dict[str, DocCommand] = {}
    for other in doc_commands():
        if other.text == cmd.text:
            break
        if other.text not in NOT_RUN and (out := writes(run_tokens(other))):
            earlier[out] = other
    paths = reads(run_tokens(cmd))
    return [earlier[p] for p in paths if p in earlier], [p for p in paths if p not in earlier]


def is_slow(cmd: DocCommand) -> bool:
    slow = _subcommand(run_tokens(cmd)) in SLOW_SUBCOMMANDS
    return slow or any(map(is_slow, producers(cmd)[0]))


def _params(slow: bool):
    return [
        pytest.param(c, id=c.where[0])
        for c in doc_commands()
        if c.text not in NOT_RUN and is_slow(c) == slow
    ]


# ------------------------------------------------------------------------------------ running


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """The folder the commands run in: configs/ and the shipped data as in the repository (read
    only), a copy of notebooks/ (a command rewrites the notebook)."""
    work = tmp_path_factory.mktemp("docs")
    (work / "configs").symlink_to(ROOT / "configs", target_is_directory=True)
    (work / "evojax_motion").mkdir()
    (work / "evojax_motion" / "data").symlink_to(ROOT / "evojax_motion" / "data", True)
    shutil.copytree(ROOT / "notebooks", work / "notebooks")
    return work


def _argv(tokens) -> list[str]:
    head = tokens[0].removeprefix(VENV_BIN)
    if head == "python":
        return [sys.executable, *tokens[1:]]
    if head == "evojax-motion":
        script = Path(sys.executable).parent / "evojax-motion"
        if script.is_file():
            return [str(script), *tokens[1:]]
        main = "import sys; from evojax_motion.cli.entry import main; sys.exit(main())"
        return [sys.executable, "-c", main, *tokens[1:]]
    pytest.fail(f"no way to run `{' '.join(tokens)}`: list it in SUBSTITUTED or NOT_RUN")


_DONE: dict[str, subprocess.CompletedProcess] = {}


def run_doc_command(cmd: DocCommand, work: Path) -> subprocess.CompletedProcess:
    """Run ``cmd`` (after what it needs) in ``work`` once; fail naming its file and line."""
    where = ", ".join(cmd.where)
    if cmd.text in _DONE:
        if _DONE[cmd.text].returncode != 0:
            pytest.fail(f"{where}: `{cmd.text}` failed (see its own test)")
        return _DONE[cmd.text]
    before, missing = producers(cmd)
    if missing:
        pytest.fail(f"{where}: `{cmd.text}` reads {missing}, which no command before it writes")
    for need in before:
        run_doc_command(need, work)
    tokens = run_tokens(cmd)
    try:
        done = subprocess.run(
            _argv(tokens), cwd=work, capture_output=True, text=True, timeout=TIMEOUT_S
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"{where}: `{cmd.text}` ran longer than {TIMEOUT_S} s")
    _DONE[cmd.text] = done
    if done.returncode != 0:
        pytest.fail(
            f"{where}: `{cmd.text}` (run as `{' '.join(tokens)}`) exited {done.returncode}:\n"
            f"{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
        )
    sub = _subcommand(tokens)
    out = writes(tokens)
    expected = {"train": f"{out}/summary.json", "report": f"{tokens[2]}/report/report.html"}
    made = expected.get(sub or "", out)
    if made is not None and not (work / made).is_file():
        pytest.fail(f"{where}: `{cmd.text}` exited 0 but did not write {made}")
    return done


# -------------------------------------------------------------------------------------- tests


def test_commands_are_found():
    """The extraction itself, on the commands this test knows to be there."""
    texts = [c.text for c in doc_commands()]
    # README's "make demo   # creates .venv, ...": the comment is no part of the command;
    # IMPORT is written over two lines joined by a backslash
    for text in ("make demo", IMPORT, TRAIN_REACH):
        assert text in texts, text
    assert not any(t.startswith("evojax_motion/data") for t in texts), texts


def test_commands_are_run_or_listed():
    """Every command runs (as written or substituted) or is listed with its reason; no table
    entry is stale; what a command reads is written by a command before it; every repository
    path a command names exists."""
    texts = {c.text for c in doc_commands()}
    stale = sorted((set(SUBSTITUTED) | set(NOT_RUN)) - texts)
    assert not stale, f"listed in SUBSTITUTED/NOT_RUN but in no document: {stale}"
    for cmd in doc_commands():
        where = ", ".join(cmd.where)
        if cmd.text not in NOT_RUN:
            _argv(run_tokens(cmd))  # a runner exists
            missing = producers(cmd)[1]
            assert not missing, (
                f"{where}: `{cmd.text}` reads {missing}, which no command before writes"
            )
        for word in cmd.tokens:  # paths (or globs), not options, synopses or code
            if "/" in word and not re.search(r"[\s=|]", word) and word[0] not in "-[":
                path = word.removeprefix("./")
                if path.startswith(("runs/", VENV_BIN)) or path == writes(cmd.tokens):
                    continue  # written by the commands
                assert glob.glob(str(ROOT / path)), f"{where}: no file {path}"


@pytest.mark.parametrize("cmd", _params(slow=False))
def test_doc_command_runs(cmd, workdir):
    run_doc_command(cmd, workdir)


@pytest.mark.slow
@pytest.mark.parametrize("cmd", _params(slow=True))
def test_doc_command_runs_slow(cmd, workdir):
    done = run_doc_command(cmd, workdir)
    if _subcommand(run_tokens(cmd)) == "catch":  # caught, not the --nearest fallback
        assert done.stdout.startswith("catch at t ="), done.stdout
