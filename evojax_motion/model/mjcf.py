"""Reading MJCF: a model file with its includes and assets as one self-contained text (`read_mjcf`),
and compiling MJCF text (`compile_mjcf`) the way every `Robot` does.

A file without includes or asset files is kept verbatim; any other one is expanded by
``MjSpec.to_xml`` with its meshes written into the text (docs/robot_models.md).
"""

from __future__ import annotations

import copy
import functools
import os
import sys
from pathlib import Path
from typing import NamedTuple
from xml.etree import ElementTree

import mujoco
import numpy as np

from evojax_motion.errors import UserError, read_user_file


def object_names(m: mujoco.MjModel, obj: mujoco.mjtObj, count: int) -> list[str]:
    """The names of objects ``0 .. count-1`` of kind ``obj`` (``#i`` for an unnamed one)."""
    return [mujoco.mj_id2name(m, obj, i) or f"#{i}" for i in range(count)]


def first_lines(err: Exception) -> str:
    """MuJoCo's message on one line (it spreads what and where over several)."""
    lines = [ln.strip() for ln in str(err).strip().splitlines() if ln.strip()]
    return "; ".join(lines[:2]) if lines else type(err).__name__


@functools.lru_cache(maxsize=8)
def _compiled(xml: str) -> mujoco.MjModel:
    """The model of ``xml``, compiled once: loading a robot reads its model up to three times
    (defaults, the robot, a rebuilt copy) and a model with meshes takes ~0.3 s to compile."""
    return mujoco.MjModel.from_xml_string(xml)


def compile_mjcf(xml: str, where: str) -> mujoco.MjModel:
    """Compile MJCF text, with constraints and contacts switched off (see `Robot.mj_model`).

    A new ``MjModel`` each call (a copy of the cached one): callers may change theirs.
    """
    try:
        m = copy.copy(_compiled(xml))
    except Exception as err:  # mujoco raises ValueError; its first lines say what is wrong
        raise UserError(f"{where}: MJCF does not compile: {first_lines(err)}") from None
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT) | int(
        mujoco.mjtDisableBit.mjDSBL_CONTACT
    )
    return m


def format_numbers(values) -> str:
    """Numbers as an MJCF attribute value, each written exactly (``repr`` of its float)."""
    return " ".join(repr(float(v)) for v in values)


class ModelText(NamedTuple):
    """What `read_mjcf` returns: self-contained MJCF text and the files it was made from."""

    xml: str  # compiles from the string alone
    files: tuple[str, ...]  # the model file first, then its includes and asset files


def read_mjcf(path: str | os.PathLike) -> ModelText:
    """Load an MJCF file as MuJoCo does (``<include>``, ``meshdir``, meshes beside the file) and
    return self-contained text for it.

    A file without includes or asset files is returned verbatim. Otherwise MuJoCo's own parse
    (``MjSpec.from_file``) is written back with ``MjSpec.to_xml`` (includes expanded; numbers to
    its 6 significant digits), each mesh file as the mesh's vertices and faces in the text. Texture
    files are left out (warned on stderr: pictures show plain colours). Height-field and skin files
    are refused (`UserError`). Dynamics never read meshes; they are kept for pictures.
    """
    path = Path(path)
    text = read_user_file(path, "MJCF")
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except Exception as err:  # mujoco raises ValueError
        raise UserError(f"{path}: MJCF does not compile: {first_lines(err)}") from None
    includes = _include_files(path)
    assets = _asset_files(spec, path)
    files = tuple(str(p) for p in (path, *includes, *(p for _, p in assets)))
    if not includes and not assets:
        return ModelText(text, files)
    return ModelText(_self_contained_xml(spec, path), files)


def _include_files(path: Path) -> list[Path]:
    """The files ``<include>``d by ``path`` and by them, as MuJoCo finds them (relative to the
    main file's folder, else to the including file's)."""
    found: list[Path] = []

    def visit(file: Path) -> None:
        try:
            root = ElementTree.parse(file).getroot()
        except (OSError, ElementTree.ParseError):
            return  # MuJoCo has read it already; this list is for the summary only
        for element in root.iter("include"):
            name = element.get("file", "")
            for folder in (path.parent, file.parent):
                candidate = folder / name
                if name and candidate.is_file():
                    if candidate not in found:
                        found.append(candidate)
                        visit(candidate)
                    break

    visit(path)
    return found


def _asset_files(spec: mujoco.MjSpec, path: Path) -> list[tuple[str, Path]]:
    """``(kind, file)`` of every asset of ``spec`` that MuJoCo reads from a file."""
    base = Path(spec.modelfiledir or path.parent)

    def where(element, attr: str, name: str) -> Path:
        folder = getattr(getattr(element, "compiler", None), attr, None)
        folder = getattr(spec, attr) if folder is None else folder
        return base / folder / name

    out: list[tuple[str, Path]] = []
    out += [("mesh", where(m, "meshdir", m.file)) for m in spec.meshes if m.file]
    out += [("hfield", where(h, "meshdir", h.file)) for h in spec.hfields if h.file]
    out += [("skin", where(s, "meshdir", s.file)) for s in spec.skins if s.file]
    for tex in spec.textures:
        names = [tex.file, *list(tex.cubefiles)]
        out += [("texture", where(tex, "texturedir", n)) for n in names if n]
    return out


def _self_contained_xml(spec: mujoco.MjSpec, path: Path) -> str:
    """``spec`` (read from ``path``) as MJCF text that needs no other file (see `read_mjcf`)."""
    for kind, items in (("hfield", spec.hfields), ("skin", spec.skins)):
        named = [h.name or h.file for h in items if h.file]
        if named:
            raise UserError(
                f"{path}: {kind} {named[0]!r} is read from a file, which cannot be stored with "
                f"the robot; expected meshes, primitive geoms and textures only"
            )
    try:
        m = spec.compile()
    except Exception as err:
        raise UserError(f"{path}: MJCF does not compile: {first_lines(err)}") from None
    for i, mesh in enumerate(spec.meshes):
        if not mesh.file:
            continue
        # MuJoCo moves a mesh to its centre of mass and principal axes (mesh_pos, mesh_quat) and
        # scales it: the compiled vertices, moved back, are the file's, scaled.
        adr, n = int(m.mesh_vertadr[i]), int(m.mesh_vertnum[i])
        fadr, nf = int(m.mesh_faceadr[i]), int(m.mesh_facenum[i])
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, m.mesh_quat[i])
        vert = m.mesh_vert[adr : adr + n].astype(np.float64) @ rot.reshape(3, 3).T + m.mesh_pos[i]
        mesh.file = ""
        mesh.content_type = ""
        mesh.scale = [1.0, 1.0, 1.0]
        mesh.refpos = [0.0, 0.0, 0.0]
        mesh.refquat = [1.0, 0.0, 0.0, 0.0]
        mesh.uservert = vert.ravel().tolist()
        mesh.userface = m.mesh_face[fadr : fadr + nf].ravel().tolist()
    dropped = [tex for tex in spec.textures if tex.file or any(tex.cubefiles)]
    if dropped:
        names = {tex.name or Path(tex.file).stem for tex in dropped}
        for material in spec.materials:
            material.textures = ["" if t in names else t for t in material.textures]
        for tex in dropped:
            spec.delete(tex)
        print(
            f"warning: {path}: texture files are not stored with the robot (pictures show plain "
            f"colours): {sorted(names)}",
            file=sys.stderr,
        )
    spec.meshdir = ""
    spec.texturedir = ""
    return spec.to_xml()
