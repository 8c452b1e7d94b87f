"""A library's assets: a folder searched for every mesh format the CLI reads, .npz arrays and .blend files (each
mesh object one asset, exported by a `blender` binary, `blend_export.py`), or a list file with one path per line;
`load_asset` reads one. A file that cannot be listed is an asset with its error, not a stop."""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from ..geometry.mesh import SUPPORTED_EXTENSIONS
from ..geometry.mesh_arrays import mesh_from_npz

#: Files a folder library is searched for (plus .gz variants of the mesh formats).
ARRAY_EXTENSION = ".npz"
BLEND_EXTENSION = ".blend"


@dataclass
class Asset:
    """One library entry. name: unique in the library (its path relative to LIBRARY, '/' -> '__', and for a
    .blend object ':OBJECT'); path: the mesh file (or the exported .npz); source: what the user has (the file, or
    'FILE.blend:OBJECT')."""

    name: str
    path: str
    source: str
    error: str | None = None  # set when the asset could not even be listed (a .blend without Blender)


def _is_mesh_file(p: Path) -> bool:
    suffixes = [s.lower() for s in p.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes = suffixes[:-1]
    return bool(suffixes) and suffixes[-1] in SUPPORTED_EXTENSIONS + (ARRAY_EXTENSION,)


def _asset_name(path: Path, root: Path, keep_suffix: bool = False) -> str:
    """The path relative to the library, '/' -> '__', without its format suffixes (.ply.gz) unless asked."""
    try:
        rel = path.relative_to(root)
    except ValueError:
        rel = Path(path.name)
    text = str(rel)
    if not keep_suffix:
        stem = rel.name.split(".")[0] or rel.name
        text = str(rel.with_name(stem))
    return text.replace(os.sep, "__")


#: A library list file names one asset per line: 16 MB is ~100,000 paths.
MAX_LIST_BYTES = 16 << 20


def discover(library: Path, work_dir: Path, blender: str | None = None) -> list[Asset]:
    """The assets of `library` (a folder or a list file, see the module docstring), in a stable order; .blend files
    are exported into `work_dir/blend/`. Raises ValueError when LIBRARY does not exist or lists nothing."""
    from .blend_export import export_blend

    library = Path(library)
    if library.is_dir():
        root, files = library, sorted(p for p in library.rglob("*") if p.is_file() and not p.name.startswith("."))
        files = [p for p in files if _is_mesh_file(p) or p.suffix.lower() == BLEND_EXTENSION]
    elif library.is_file():
        if library.stat().st_size > MAX_LIST_BYTES:
            raise ValueError(f"{library}: a library list is at most {MAX_LIST_BYTES} bytes (one path per line)")
        root = library.parent
        lines = [ln.strip() for ln in library.read_text().splitlines()]
        files = [(root / ln) if not Path(ln).is_absolute() else Path(ln) for ln in lines if ln and not ln.startswith("#")]
    else:
        raise ValueError(f"{library}: no such folder or list file")
    assets = []
    stems = [_asset_name(p, root) for p in files]
    for p, stem in zip(files, stems):
        name = stem if stems.count(stem) == 1 else _asset_name(p, root, keep_suffix=True)  # blob.ply beside blob.obj
        if p.suffix.lower() != BLEND_EXTENSION:
            assets.append(Asset(name=name, path=str(p), source=str(p)))
            continue
        try:
            digest = hashlib.sha256(str(p.resolve()).encode()).hexdigest()[:10]
            for obj, npz in export_blend(p, work_dir / "blend" / f"{p.stem}-{digest}", blender):
                assets.append(Asset(name=f"{name}:{obj}", path=str(npz), source=f"{p}:{obj}"))
        except ValueError as exc:
            assets.append(Asset(name=name, path=str(p), source=str(p), error=str(exc)))
    if not assets:
        raise ValueError(f"{library}: no mesh files found (looked for {', '.join(SUPPORTED_EXTENSIONS)}, "
                         f"{ARRAY_EXTENSION}, {BLEND_EXTENSION})")
    return assets


def load_asset(path: str, name: str):
    """The asset's mesh (a mesh file, or an .npz with `vertices` and `faces`). Raises ValueError (MeshError)."""
    from ..geometry.mesh import load_mesh

    if path.lower().endswith(ARRAY_EXTENSION):
        return mesh_from_npz(path, name)
    return load_mesh(path)
