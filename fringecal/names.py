"""Names that become paths, and writes that stay in their folder.

Scanner, sensor, measurement, position and object names become file and folder names
(a run's store ``measurements/<measurement>-<scanner>.zarr``, a data set's
``measurements/<measurement>/<scanner>/``, an export's ``<scanner>.yml``). Each must
therefore be one safe path component, checked wherever a name enters -- a table
column (:func:`fringecal.schemas.validate_table`), a rig built from a calibration
file or an OpenCV file (:class:`fringecal.rig.Rig`), a data set's folder
(:mod:`fringecal.dataset`), a configuration -- by :func:`check_name`:

* not empty, at most :data:`MAX_NAME_CHARS` characters (a run's temporary store name
  joins two names and 30 characters more, and must stay within the file system's 255
  bytes a name);
* no ``/`` or ``\\``, no control character (NUL, tab, line feed, ...);
* not ``.`` or ``..`` and not starting with ``.`` (hidden names are ignored in data
  sets and are the writers' temporaries), no leading or trailing blank.

Every writer that builds a path from a name also joins it with :func:`confined`,
which refuses a result outside the output folder (a second line of defence: a name
that escaped the first check, or a symbolic link inside the output folder that
leads out of it).

>>> check_name("scanner1", "scanner")
'scanner1'
>>> check_name("../../tmp/x", "scanner")
Traceback (most recent call last):
...
fringecal.names.UnsafeNameError: scanner '../../tmp/x': a name must be one folder or file name: no '/'
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

__all__ = ["MAX_NAME_CHARS", "OutsideFolderError", "UnsafeNameError", "check_name", "confined", "name_problem"]

#: the longest name: two names, a hyphen and a temporary's ``.`` ``.zarr.tmp-<12 hex>``
#: (24 characters) stay within 255 bytes even in 2-byte UTF-8 characters
MAX_NAME_CHARS = 100


class UnsafeNameError(ValueError):
    """A name that cannot be one path component; the message names where it came from."""


class OutsideFolderError(ValueError):
    """A write that would land outside its output folder."""


def name_problem(name) -> str | None:
    """Why ``name`` is not one safe path component, or None when it is."""
    if not isinstance(name, str):
        return f"expected text, got {type(name).__name__}"
    if not name:
        return "a name must not be empty"
    if len(name) > MAX_NAME_CHARS:
        return f"{len(name)} characters; a name has at most {MAX_NAME_CHARS} (it becomes a file name)"
    for bad, what in (("/", "'/'"), ("\\", "'\\'")):
        if bad in name:
            return f"a name must be one folder or file name: no {what}"
    control = next((c for c in name if ord(c) < 32 or ord(c) == 127), None)
    if control is not None:
        return f"a name must not hold control characters (found {control!r})"
    if name in (".", ".."):
        return f"{name!r} is not a name (it means a folder itself or its parent)"
    if name.startswith("."):
        return "a name must not start with '.' (hidden names are ignored and used for temporaries)"
    if name != name.strip():
        return "a name must not start or end with a blank"
    return None


def check_name(name, what: str, where: str = "") -> str:
    """``name`` if it is one safe path component (see the module notes), else
    :class:`UnsafeNameError` naming ``what`` (``"scanner"``) and ``where`` (a file)."""
    problem = name_problem(name)
    if problem is None:
        return name
    shown = name if not isinstance(name, str) or len(name) <= 60 else name[:40] + "..." + name[-10:]
    prefix = f"{where}: " if where else ""
    raise UnsafeNameError(f"{prefix}{what} {shown!r}: {problem}")


def confined(root, *parts) -> Path:
    """``root`` joined with ``parts``, refused (:class:`OutsideFolderError`) unless the
    result lies inside ``root`` once ``..`` and symbolic links are resolved."""
    root = Path(root)
    path = root.joinpath(*parts)
    base = Path(os.path.realpath(root))
    target = Path(os.path.realpath(path))
    if target != base and base not in target.parents:
        raise OutsideFolderError(f"{path}: would be written outside {root} (it resolves to {target}); "
                                 "nothing was written there")
    return path


def not_a_file(path) -> str | None:
    """What ``path`` is when it is not a regular file (or a link to one) that can be read
    -- "a symbolic link loop", "a FIFO (named pipe)", "a device" -- else None. Never
    opens it (opening a FIFO to read waits for a writer forever)."""
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError as err:
        if err.errno == errno.ELOOP:
            return "a symbolic link loop"
        if path.is_symlink():
            return f"a broken symbolic link (to {os.readlink(path)})"
        return None  # missing: the caller says so
    mode = st.st_mode
    for test, kind in ((stat.S_ISREG, None), (stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return "not a regular file"
