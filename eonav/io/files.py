"""Files named on a command line, opened so that no path can hang, exhaust or crash the command.

An input must be a regular file (a directory, a FIFO, a device such as ``/dev/zero`` or a socket is refused with
what it is), is opened non-blocking (a FIFO with no writer never blocks the open) and is read up to a byte limit
(a file that grows while read cannot make the read endless). An output path is checked before any work is done
(not a directory, its folder can be made and a file created in it) and written under exactly the name given.
Every failure is an ``InputError`` naming the file, what it is and what was expected.
"""
from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

from eonav import InputError

KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
         (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def kind_of(mode: int) -> str:
    """What a file of this ``st_mode`` is, in words ("a regular file", "a directory", ...)."""
    if stat.S_ISREG(mode):
        return "a regular file"
    return next((name for test, name in KINDS if test(mode)), "not a regular file")


def read_regular_file(path, what: str, max_bytes: int) -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` bytes; ``what`` names it in errors ("pair file")."""
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise InputError(f"{what} not found: {p}") from None
    except OSError as e:
        raise InputError(f"{what} {p}: cannot open ({e.strerror or e})") from None
    except ValueError as e:                 # a NUL byte in the path
        raise InputError(f"{what} {str(p)!r}: not a usable path ({e})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"{what} {p}: is {kind_of(st.st_mode)}, expected a regular file")
        if st.st_size > max_bytes:
            raise InputError(f"{what} {p}: {st.st_size} bytes, more than the {max_bytes} bytes allowed")
        chunks, n = [], 0
        while n <= max_bytes:
            b = os.read(fd, min(1 << 20, max_bytes + 1 - n))
            if not b:
                break
            chunks.append(b)
            n += len(b)
    except OSError as e:
        raise InputError(f"{what} {p}: cannot read ({e.strerror or e})") from None
    finally:
        os.close(fd)
    data = b"".join(chunks)
    if len(data) > max_bytes:
        raise InputError(f"{what} {p}: more than the {max_bytes} bytes allowed (it grew while read)")
    return data


def check_output(path, what: str = "--out") -> Path:
    """Fail before any work when ``path`` cannot be written as a file: it is a directory or a FIFO, its folder
    cannot be made, or no file can be created there (e.g. under ``/proc``). Makes the missing folders."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        st = None
    except (OSError, ValueError) as e:      # (ValueError: a NUL byte in the path)
        raise InputError(f"{what} {str(p)!r}: cannot use this path ({getattr(e, 'strerror', None) or e})") from None
    if st is not None and not (stat.S_ISREG(st.st_mode) or stat.S_ISCHR(st.st_mode)):   # /dev/null is fine
        raise InputError(f"{what} {p}: is {kind_of(st.st_mode)}, expected a file name (e.g. range.npz)")
    if st is not None and not os.access(p, os.W_OK):
        raise InputError(f"{what} {p}: exists and is not writable")
    if st is None:
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            fd, probe = tempfile.mkstemp(dir=p.parent, prefix=".eonav-probe-")
            os.close(fd)
            os.unlink(probe)
        except OSError as e:
            raise InputError(f"{what} {p}: cannot create a file in {p.parent} ({e.strerror or e})") from None
    return p


def write_npz(path, arrays: dict, what: str = "--out") -> Path:
    """``arrays`` as a compressed .npz under exactly ``path`` (numpy would append .npz to a name without it)."""
    import numpy as np
    p = check_output(path, what)
    try:
        with open(p, "wb") as f:
            np.savez_compressed(f, **arrays)
    except OSError as e:
        raise InputError(f"{what} {p}: cannot write ({e.strerror or e})") from None
    return p
