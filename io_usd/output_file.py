"""Files a command writes: whole or not at all, and checked before the work that fills them.

A path that could never take the file (a folder, a folder that cannot be written, a wrong extension)
fails in check_output_path before minutes of simulation or rendering, with one line naming the path
and the reason. The file itself is written under a temporary name beside it (temporary_beside) and
renamed onto the path only when complete (publish), so a failure part way leaves neither a partial
file nor a changed old one; write_whole does all three for a file written in one call.
"""

import os
import tempfile

from sim.errors import InputError


def _choices(extensions):
    names = list(extensions)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " or " + names[-1]


def check_output_path(path, extensions, what="the output"):
    """Return `path` if a file may be written there, else raise InputError(path, None, reason).

    extensions: the accepted endings, lower case with the dot (".png", ...); what: the file's role in
    the reason ("the preview"). The path must not be a folder, the nearest existing folder above it
    must take a new file (probed by making and removing one), and no file may stand where a folder
    is needed. Nothing is left behind, not even the folders the writer will make."""
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in extensions:
        got = f", not {ext}" if ext else ""
        raise InputError(path, None, f"{what} must end in {_choices(extensions)}{got}")
    if os.path.isdir(path):
        raise InputError(path, None, "is a folder; name a file in it")
    _check_folder_above(path, os.path.dirname(os.path.abspath(path)))
    return path


def is_input(output, given):
    """Whether writing `output` would replace the existing file `given` (the same path, or a link
    to it): a command's output must never be one of its own inputs."""
    return os.path.exists(given) and os.path.realpath(given) == os.path.realpath(output)


def check_output_folder(path):
    """Return `path` if a folder may be made there (or an existing one filled), else raise
    InputError(path, None, reason): the path is not a file and the nearest existing folder at or
    above it takes a new file."""
    path = os.fspath(path)
    if os.path.lexists(path) and not os.path.isdir(path):
        raise InputError(path, None, "exists and is not a folder")
    _check_folder_above(path, os.path.abspath(path))
    return path


def _check_folder_above(path, folder):
    """InputError naming path unless the nearest existing folder at or above `folder` takes a new file."""
    existing = folder
    while not os.path.lexists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        raise InputError(path, None, f"{existing} is not a folder")
    try:
        handle, probe = tempfile.mkstemp(prefix=".cfx-probe-", dir=existing)
        os.close(handle)
        os.remove(probe)
    except OSError as err:
        raise InputError(path, None, f"cannot write in {existing}: {err.strerror or err}") from None


def temporary_beside(path, suffix=None):
    """A temporary name beside `path` for its file while it is written (its folders made), ending in
    suffix (default path's own extension, which some writers read to pick the format)."""
    path = os.path.abspath(os.fspath(path))
    folder, base = os.path.split(path)
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as err:
        raise InputError(path, None, f"cannot make its folder: {err.strerror or err}") from None
    ext = os.path.splitext(base)[1] if suffix is None else suffix
    tmp = os.path.join(folder, f".{base}.partial-{os.getpid()}{ext}")
    if os.path.exists(tmp):
        os.remove(tmp)
    return tmp


def publish(tmp, path):
    """Rename the finished temporary file onto `path`; on failure remove it and raise InputError
    naming `path` (never the temporary name)."""
    try:
        os.replace(tmp, path)
    except OSError as err:
        discard(tmp)
        reason = "is a folder; name a file in it" if os.path.isdir(path) else f"cannot write it: {err.strerror or err}"
        raise InputError(os.fspath(path), None, reason) from None


def discard(tmp):
    """Remove a temporary file if it is there."""
    if os.path.exists(tmp):
        os.remove(tmp)


def write_whole(path, write, suffix=None):
    """Call write(temporary path), then publish it onto `path`; any failure leaves nothing behind.
    Returns path."""
    tmp = temporary_beside(path, suffix)
    try:
        write(tmp)
        publish(tmp, path)
    except OSError as err:
        raise InputError(os.fspath(path), None, f"cannot write it: {err.strerror or err}") from None
    finally:
        discard(tmp)
    return path


__all__ = ["check_output_folder", "check_output_path", "discard", "publish", "temporary_beside", "write_whole"]
