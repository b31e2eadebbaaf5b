"""Built assets kept on disk between runs: the mannequin, fitted garments, grown grooms, sphere trees.

Building them takes seconds of a run's start (marching cubes over the body's field, a garment's
cross-sections, a groom grown in a hundred collision passes, a greedy cover of a head with spheres)
and gives the same arrays every time for the same inputs. Each entry is an .npz named by its kind
and two hashes: one of the engine's own sources and the versions of the libraries that computed it,
one of every input. Any edit to the engine, or another numpy, scipy, trimesh, scikit-image or Warp,
makes every entry stale; stale entries are deleted when a fresh one is written, so the folder holds
the current code's assets only. Files not named as entries are never listed, read or deleted.

Where: $CFX_CACHE_DIR, else $XDG_CACHE_HOME/warp-cfx, else ~/.cache/warp-cfx. CFX_CACHE_DIR=off
builds everything every time. A folder that cannot be written only costs the time: runs never fail
for the cache's sake, and an unreadable entry is built again.
"""

import dataclasses
import functools
import hashlib
import os
import re
import time
import zipfile
from pathlib import Path

import numpy as np

SUFFIX = ".npz"
# KIND-SOURCES-INPUTS.npz, and .KIND-SOURCES-INPUTS.PID.tmp.npz while one is written
_ENTRY = re.compile(r"^[a-z_]+-[0-9a-f]{16}-[0-9a-f]{24}\.npz$")
_WRITING = re.compile(r"^\.[a-z_]+-[0-9a-f]{16}-[0-9a-f]{24}\.\d+\.tmp\.npz$")
_PACKAGES = ("sim", "warp_kernels")
_LIBRARIES = ("numpy", "scipy", "trimesh", "skimage", "warp")


def cache_dir():
    """The cache folder (not created here), or None when CFX_CACHE_DIR=off."""
    chosen = os.environ.get("CFX_CACHE_DIR")
    if chosen is not None:
        return None if chosen.strip().lower() in ("", "off", "0", "none") else Path(chosen).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "warp-cfx"


@functools.lru_cache(maxsize=1)
def source_digest():
    """Hash of every Python source of the engine and the versions of the libraries it builds with."""
    return digest_sources(Path(__file__).resolve().parent.parent)


def digest_sources(root):
    """source_digest of the engine's packages under `root` (a checkout or site-packages)."""
    from importlib import metadata

    from . import __version__

    h = hashlib.sha256(f"warp-cfx {__version__};".encode())  # all there is when sources are not files
    root = Path(root)
    for package in _PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            h.update(path.relative_to(root).as_posix().encode())
            h.update(path.read_bytes())
    for name in _LIBRARIES:
        try:
            version = metadata.version({"skimage": "scikit-image", "warp": "warp-lang"}.get(name, name))
        except metadata.PackageNotFoundError:
            version = "-"
        h.update(f"{name}={version};".encode())
    return h.hexdigest()[:16]


def _feed(h, value):
    """Hash `value` (arrays, numbers, strings, None, and tuples, lists, dicts and dataclasses of them)."""
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        h.update(f"array{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    elif isinstance(value, (bool, int, float, str, type(None), np.generic)):
        h.update(f"{type(value).__name__}:{value!r};".encode())
    elif isinstance(value, (tuple, list)):
        h.update(f"seq{len(value)}(".encode())
        for item in value:
            _feed(h, item)
        h.update(b")")
    elif isinstance(value, dict):
        h.update(f"dict{len(value)}(".encode())
        for key in sorted(value, key=str):
            _feed(h, str(key))
            _feed(h, value[key])
        h.update(b")")
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        h.update(f"{type(value).__qualname__}(".encode())
        for f in dataclasses.fields(value):
            _feed(h, f.name)
            _feed(h, getattr(value, f.name))
        h.update(b")")
    else:
        raise TypeError(f"asset_cache cannot hash a {type(value).__name__}")


def input_digest(inputs):
    h = hashlib.sha256()
    _feed(h, inputs)
    return h.hexdigest()[:24]


def entry_path(kind, inputs):
    """Where the entry for `kind` built from `inputs` lives (None when the cache is off)."""
    folder = cache_dir()
    if folder is None:
        return None
    return folder / f"{kind}-{source_digest()}-{input_digest(inputs)}{SUFFIX}"


def cached_arrays(kind, inputs, build):
    """The dict of NumPy arrays `build()` returns for `inputs`, read from the cache when it holds them.

    kind: a short name for the entry ("body", "groom", ...); inputs: everything the result depends
    on besides the engine's code (see _feed for what can be hashed).
    """
    path = entry_path(kind, inputs)
    if path is not None:
        try:
            with np.load(path, allow_pickle=False) as stored:
                return {key: stored[key] for key in stored.files}
        except FileNotFoundError:
            pass
        except (OSError, ValueError, EOFError, zipfile.BadZipFile):
            pass  # a torn or foreign file: built again and replaced below
    arrays = {key: np.asarray(value) for key, value in build().items()}
    if path is not None:
        _store(path, arrays)
    return arrays


def _store(path, arrays):
    temporary = path.with_name(f".{path.stem}.{os.getpid()}.tmp{SUFFIX}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(temporary, **arrays)
        os.replace(temporary, path)  # whole or not at all: readers never see a half-written entry
    except OSError:
        _remove(temporary)
        return
    current = f"-{source_digest()}-"
    for old in path.parent.glob(f"*{SUFFIX}"):
        if _WRITING.match(old.name):  # another run's write in progress, or one killed mid-write long ago
            try:
                if time.time() - old.stat().st_mtime > 3600.0:
                    _remove(old)
            except OSError:
                pass
        elif _ENTRY.match(old.name) and current not in old.name:
            _remove(old)  # built by other code or other libraries


def _remove(path):
    try:
        path.unlink(missing_ok=True)
    except OSError:  # not ours to delete, or its folder is gone: left as it is
        pass


def entries():
    """(path, bytes) of every entry in the cache folder, current or not."""
    folder = cache_dir()
    if folder is None or not folder.is_dir():
        return []
    found = []
    for path in sorted(folder.glob(f"*{SUFFIX}")):
        try:
            if _ENTRY.match(path.name):
                found.append((path, path.stat().st_size))
        except FileNotFoundError:  # deleted by another run since the listing
            continue
    return found


def clear():
    """Delete every entry; returns how many were deleted."""
    removed = 0
    for path, _ in entries():
        path.unlink(missing_ok=True)
        removed += 1
    return removed
