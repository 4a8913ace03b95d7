"""Measurement stores: one zarr v3 store per measurement, written atomically.

A store is written under a hidden temporary sibling name (``.M.zarr.tmp-<id>``),
then finalised -- a manifest of every variable's chunk files (count and bytes), the
SHA-256 of every chunk file and of each array's metadata (``fringecal_digests``) and
the completion marker ``fringecal_complete = true`` go into the root attributes,
written last together with the consolidated metadata -- and only then renamed to
its final name. A crash leaves at most a hidden temporary folder; a folder at the
final name without the marker, or whose files disagree with the manifest, is
refused by :func:`open_store` with a message naming the store.

Content is checked on read: :func:`open_store` and :func:`copy_store` (and
:func:`verify_store`) hash every file the digests list and refuse a store whose
bytes changed since it was written, naming the file -- one flipped byte in a chunk
would otherwise decode to other numbers without a word (a chunk's size does not
change). A store is hashed once per process while its files' size, modification
and change times and inode stay the same (:data:`_VERIFIED`); the change time
(ctime) cannot be set back by a program, so a same-size rewrite with its mtime
restored is hashed again. Stores written before the digests existed carry none and
are checked by size only.

Stores open with plain ``xarray.open_zarr(path)``; :func:`open_store` adds the
checks. Maps are float32 (or bool) of shape (H, W) on dims ``("v", "u")`` (camera
row, column), chunked 512 x 512 and compressed with Blosc/lz4.

A complete store is never changed: maps derived from it (point clouds, labels) go to
stores of their own. :func:`copy_store` copies one (hard links where possible).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import threading
import uuid
import warnings
from pathlib import Path
from typing import Mapping

import xarray as xr
import zarr
from zarr.codecs import BloscCodec

__all__ = ["StoreError", "write_store", "open_store", "is_complete", "store_attributes", "copy_store", "store_encoding",
           "verify_store", "COMPLETE_ATTR", "MANIFEST_ATTR", "DIGESTS_ATTR"]

# Stores are written with consolidated metadata on purpose (one read opens a store);
# zarr warns on every write and open that v3 has no such spec yet.
warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part", category=UserWarning)

COMPLETE_ATTR = "fringecal_complete"
MANIFEST_ATTR = "fringecal_manifest"
DIGESTS_ATTR = "fringecal_digests"
MAP_CHUNK = 512
FRAME_CHUNK = 256
POINT_CHUNK = 1 << 20


class StoreError(ValueError):
    """A store that is missing, incomplete or corrupt; the message names it."""


def store_encoding(ds: xr.Dataset) -> dict:
    """Chunks and compression per variable: (512, 512) tiles for maps, (all frames,
    256, 256) blocks for frame stacks (a block decodes on its own), 2**20 points of a
    point cloud's 1-D fields, Blosc/lz4 with
    byte shuffle (a 2048 px measurement's maps: 0.26 s and 97 MB against 0.37 s and
    91 MB with zstd level 3; writing stores dominates processing, so speed wins)."""
    enc = {}
    for name, var in ds.data_vars.items():
        if var.ndim == 1:
            chunks = (max(1, min(POINT_CHUNK, var.shape[0])),)
        elif var.ndim == 2:
            chunks = tuple(min(MAP_CHUNK, n) for n in var.shape)
        elif var.ndim == 3:
            chunks = (var.shape[0],) + tuple(min(FRAME_CHUNK, n) for n in var.shape[1:])
        else:
            chunks = var.shape
        shuffle = "bitshuffle" if var.dtype == bool else "shuffle"
        enc[name] = {"chunks": chunks,
                     "compressors": (BloscCodec(cname="lz4", clevel=5, shuffle=shuffle),)}
    return enc


def write_store(path, ds: xr.Dataset, overwrite: bool = True) -> Path:
    """Write ``ds`` as a complete zarr v3 store at ``path`` (atomically).

    Attributes must be JSON-native (checked). An existing store at ``path`` is
    replaced only once the new one is complete.
    """
    path = Path(path)
    _check_json(ds.attrs, path)
    if path.exists() and not overwrite:
        raise StoreError(f"{path}: exists (pass overwrite=True to replace it)")
    tmp = _tmp_sibling(path, "tmp")
    try:
        ds.to_zarr(tmp, mode="w-", zarr_format=3, consolidated=False, encoding=store_encoding(ds))
        _finalise(tmp)
        _swap_in(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    _remember_verified(path)
    return path


def is_complete(path) -> bool:
    """True if ``path`` is a finished store whose files match its manifest."""
    try:
        _check_complete(Path(path))
    except StoreError:
        return False
    return True


def store_attributes(path) -> dict:
    """Attributes of a complete store, read from its metadata alone (no arrays opened).

    Raises StoreError if the store is missing, incomplete or corrupt.
    """
    path = Path(path)
    _check_complete(path)
    return json.loads((path / "zarr.json").read_text())["attributes"]


def open_store(path, verify: bool = False) -> xr.Dataset:
    """Open a complete store lazily; refuse incomplete or corrupt ones.

    ``verify=True`` also reads every chunk (catches damaged chunk contents).
    """
    path = Path(path)
    _check_complete(path)
    verify_store(path)
    try:
        ds = xr.open_zarr(path, consolidated=True)
    except Exception as err:
        raise StoreError(f"{path}: corrupt store ({type(err).__name__}: {err})") from None
    if verify:
        for name, var in ds.variables.items():
            try:
                var.values
            except Exception as err:
                raise StoreError(f"{path}: variable {name!r} is corrupt ({type(err).__name__}: {err})") from None
    return ds


def copy_store(src, dst) -> Path:
    """Copy a complete store to ``dst`` atomically; chunk files are hard links where the
    file system allows (stores are never edited in place, so the copy cannot change)."""
    src, dst = Path(src), Path(dst)
    _check_complete(src)
    verify_store(src)

    def link(s, d):
        try:
            return os.link(s, d)
        except OSError:
            return shutil.copy2(s, d)

    tmp = _tmp_sibling(dst, "tmp")
    try:
        shutil.copytree(src, tmp, copy_function=link, ignore=lambda d, names: [n for n in names if n.startswith(".")])
        _swap_in(tmp, dst)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dst


def _tmp_sibling(path: Path, tag: str) -> Path:
    return path.parent / f".{path.name}.{tag}-{uuid.uuid4().hex[:12]}"


def _check_json(attrs: Mapping, path: Path) -> None:
    try:
        text = json.dumps(attrs, allow_nan=False)
    except (TypeError, ValueError) as err:
        raise StoreError(f"{path}: attributes must be JSON-native ({err})") from None
    if json.loads(text) != dict(attrs):
        raise StoreError(f"{path}: attributes do not survive a JSON round trip (tuples or non-string keys?)")


def _manifest(path: Path) -> dict[str, list[int]]:
    """Number of files and bytes under every array folder (excluding its metadata)."""
    out = {}
    for entry in sorted(path.iterdir()):
        if entry.is_dir() and (entry / "zarr.json").exists():
            n = size = 0
            for root, _, files in os.walk(entry):
                for f in files:
                    if root == str(entry) and f == "zarr.json":
                        continue
                    n += 1
                    size += os.path.getsize(os.path.join(root, f))
            out[entry.name] = [n, size]
    return out


def _content_files(path: Path) -> list[str]:
    """Relative paths of every file of a store but the root's ``zarr.json`` (which holds
    the digests), hidden ones left out."""
    out = []
    for root, dirs, files in os.walk(path):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        rel = Path(root).relative_to(path)
        out += [str(rel / f) if str(rel) != "." else f for f in sorted(files) if not f.startswith(".")]
    return [f for f in out if f != "zarr.json"]


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def _finalise(tmp: Path) -> None:
    group = zarr.open_group(tmp, mode="r+", zarr_format=3)
    digests = {rel: _sha256(tmp / rel) for rel in _content_files(tmp)}
    group.attrs.update({MANIFEST_ATTR: _manifest(tmp), DIGESTS_ATTR: digests, COMPLETE_ATTR: True})
    zarr.consolidate_metadata(tmp)


#: stores whose content this process has checked: path -> the stat signature then
_VERIFIED: dict[str, str] = {}
_VERIFIED_LOCK = threading.Lock()


def _signature(path: Path, files: list[str]) -> str:
    h = hashlib.sha256()
    for rel in [*files, "zarr.json"]:
        st = (path / rel).stat()
        h.update(f"{rel}\0{st.st_size}\0{st.st_mtime_ns}\0{st.st_ctime_ns}\0{st.st_ino}\n".encode())
    return h.hexdigest()


def _remember_verified(path: Path) -> None:
    """A store this process has just written and hashed (:func:`_finalise`) counts as
    checked by :func:`verify_store` while its files' stat signatures are unchanged (its
    first reader need not hash its chunks again)."""
    try:
        signature = _signature(path, _content_files(path))
    except OSError:
        return
    with _VERIFIED_LOCK:
        _VERIFIED[str(path.resolve())] = signature


def verify_store(path) -> None:
    """Refuse (:class:`StoreError`, naming the file) a complete store whose files are not
    the bytes its digests list: a changed, missing or added file. No-op for a store
    written before stores carried digests."""
    path = Path(path)
    doc = _metadata(path)
    expected = (doc.get("attributes") or {}).get(DIGESTS_ATTR)
    if not isinstance(expected, dict):
        return
    actual = _content_files(path)
    key = str(path.resolve())
    try:
        signature = _signature(path, actual)
    except OSError as err:
        raise StoreError(f"{path}: unreadable store ({err.strerror or err})") from None
    with _VERIFIED_LOCK:
        if _VERIFIED.get(key) == signature:
            return
    for rel in sorted(set(expected) | set(actual)):
        if rel not in actual:
            raise StoreError(f"{path / rel}: missing from the store (it was written with it); the store is corrupt: "
                             "write it again")
        if rel not in expected:
            raise StoreError(f"{path / rel}: not part of the store as written (an added file); the store is corrupt: "
                             "write it again")
        if _sha256(path / rel) != expected[rel]:
            raise StoreError(f"{path / rel}: changed since the store was written (its SHA-256 differs from the "
                             "store's digest: a damaged or edited file); write the store again")
    with _VERIFIED_LOCK:
        _VERIFIED[key] = signature


def _swap_in(tmp: Path, path: Path) -> None:
    if path.exists():
        old = _tmp_sibling(path, "old")
        os.rename(path, old)
        os.rename(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(tmp, path)


def _metadata(path: Path) -> dict:
    meta = path / "zarr.json"
    if not path.is_dir():
        raise StoreError(f"{path}: no such store")
    try:
        doc = json.loads(meta.read_text())
    except FileNotFoundError:
        raise StoreError(f"{path}: not a zarr store (no zarr.json)") from None
    except (ValueError, UnicodeDecodeError) as err:
        raise StoreError(f"{path}: corrupt store metadata ({err})") from None
    return doc if isinstance(doc, dict) else {}


def _check_complete(path: Path) -> None:
    doc = _metadata(path)
    attrs = doc.get("attributes", {}) if isinstance(doc, dict) else {}
    if attrs.get(COMPLETE_ATTR) is not True:
        raise StoreError(f"{path}: incomplete store (no completion marker; its writing was interrupted or it was "
                         "not written by fringecal); delete it and write it again")
    expected = attrs.get(MANIFEST_ATTR, {})
    actual = _manifest(path)
    for name in sorted(set(expected) | set(actual)):
        if name not in actual:
            raise StoreError(f"{path}: corrupt store: variable {name!r} is missing")
        if name not in expected:
            raise StoreError(f"{path}: corrupt store: variable {name!r} is not in the manifest")
        if actual[name] != expected[name]:
            (n0, b0), (n1, b1) = expected[name], actual[name]
            raise StoreError(f"{path}: corrupt store: variable {name!r} has {n1} chunk files / {b1} bytes, "
                             f"the manifest says {n0} / {b0}")
