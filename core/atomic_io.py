"""Writing outputs so that nothing is lost: one atomic, verified write for every file UniPixie makes.

Every output (``.blend``, PC2, ``.npz``, JSON, PNG, CSV, HTML, model weights) is written the same way:

1. into a temporary file with a unique name (``.NAME.XXXXXXXX.tmp.EXT``) in the directory of the
   target — two processes never share a temporary file, and the final rename stays on one file
   system;
2. flushed to the disk (``fsync``) and **checked**: not empty, the size the writer promised, and
   readable as its kind (an ``.npz`` opens as a zip archive with the keys written, JSON parses, a
   PNG ends with its ``IEND`` chunk, a ``.blend`` starts with Blender's header and ends with its
   ``ENDB`` block, a PC2 cache has the size its header promises);
3. renamed over the target (``os.replace``, atomic on POSIX and Windows).

If anything fails — a full disk, a read-only file system, a missing permission, Ctrl-C, a check —
the temporary file is removed, the target keeps its old content (or stays absent), and the
failure is one :class:`~unipixie.core.errors.UserError` naming the path and the cause.  No
partial file is ever left under a final name.

A target that is a symbolic link is written *through* the link (the link's target is replaced, the
link stays); :func:`output_path` is the one place that resolves it, so the "would overwrite its
input" check (:func:`refuse_overwriting_inputs`) compares real files, hard links included.

Before long work, :func:`check_writable` tries the output location (a real probe file, so a
read-only file system is found even by root) and its free space, and :class:`OutputLock` marks an
output as taken for the run: a second run writing the same output at the same time is refused
with a message naming the first one's process id.

Blender-free; the ``.blend`` writer is :func:`unipixie.core.blender_io.blend_file.save_blend`,
which uses :func:`atomic_path` with :func:`check_blend`.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import shutil
import stat
import tempfile
import zipfile
from pathlib import Path
from typing import Callable, Iterable, Iterator, Optional

from .errors import UserError

FREE_SPACE_MARGIN = 16 * 1024 * 1024
"""Bytes kept free on top of an output's estimated size when :func:`check_writable` checks the space."""
LOCK_SUFFIX = ".unipixie-lock"
TEMP_MARK = ".tmp"

_REMEDIES = {
    errno.ENOSPC: "the disk is full; free some space or choose another output location",
    errno.EDQUOT: "the disk quota is used up; free some space or choose another output location",
    errno.EROFS: "the file system is read-only; choose another output location",
    errno.EACCES: "permission denied; choose a location you may write to",
    errno.EPERM: "permission denied; choose a location you may write to",
    errno.EFBIG: "the file is larger than the file system or the process's file-size limit (ulimit -f) allows",
    errno.ENAMETOOLONG: "the path is too long; choose a shorter name",
    errno.ENOTDIR: "a part of the path is a file, not a folder",
    errno.EISDIR: "the path is a folder; give a file name",
}


def describe_os_error(exc: BaseException) -> str:
    """The cause of an ``OSError`` in words, with a remedy where one is known."""
    if isinstance(exc, OSError):
        text = exc.strerror or str(exc) or type(exc).__name__
        remedy = _REMEDIES.get(exc.errno or -1)
        return f"{text} ({remedy})" if remedy else text
    return str(exc) or type(exc).__name__


def write_error(path, exc: BaseException, what: str = "write") -> UserError:
    """A :class:`UserError` ``cannot write PATH: CAUSE`` for an OS-level failure."""
    return UserError(f"cannot {what} {path}: {describe_os_error(exc)}")


# --------------------------------------------------------------------------- paths
def output_path(path) -> Path:
    """The file a write to ``path`` really changes: ``~`` expanded, symbolic links resolved (also
    in the parent folders), made absolute.  A link is written through, never replaced."""
    return Path(os.path.realpath(os.path.expanduser(os.fspath(path))))


def same_file(a, b) -> bool:
    """True when ``a`` and ``b`` name the same file: the same path after resolving links, or the
    same inode (hard links, bind mounts)."""
    ra, rb = output_path(a), output_path(b)
    if ra == rb:
        return True
    try:
        return os.path.samefile(ra, rb)
    except OSError:
        return False


def refuse_overwriting_inputs(output, inputs: Iterable, what: str = "output") -> None:
    """Refuse an output that is (a link to, or a hard link of) one of the inputs."""
    for inp in inputs:
        if inp is None or inp == "":
            continue
        if same_file(output, inp):
            how = ""
            if os.path.islink(os.path.expanduser(os.fspath(output))):
                how = " (it is a symbolic link to it)"
            elif output_path(output) != output_path(inp):
                how = " (it is a hard link of it)"
            raise UserError(f"the {what} {output} would overwrite the input {inp}{how}; choose another {what}")


def _existing_ancestor(p: Path) -> Path:
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    return p


# --------------------------------------------------------------------------- checks before long work
def check_writable(path, need_bytes: int = 0, *, directory: bool = False, what: str = "output") -> Path:
    """Check, before any long work, that ``path`` can be written: its folder exists or can be made,
    a file can really be created there (a probe file, created and removed), an existing target is a
    file (a folder with ``directory=True``) that is not read-only, and the file system has
    ``need_bytes`` plus :data:`FREE_SPACE_MARGIN` free.  Returns :func:`output_path` of ``path``.
    Raises :class:`UserError` naming the path, the cause and the remedy.
    """
    real = output_path(path)
    if real.exists():
        if directory and not real.is_dir():
            raise UserError(f"the {what} {path} exists and is not a folder; give a folder (or a new name)")
        if not directory and real.is_dir():
            raise UserError(f"the {what} {path} is a folder; give a file name")
        if not directory and not os.access(real, os.W_OK):
            raise UserError(f"the {what} {path} is read-only; make it writable or choose another {what}")
    folder = real if directory else real.parent
    base = _existing_ancestor(folder)
    if not base.is_dir():
        raise UserError(f"cannot write the {what} {path}: {base} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".unipixie-probe.", dir=base)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise UserError(f"cannot write the {what} {path}: {describe_os_error(exc)}") from None
    if need_bytes > 0 or FREE_SPACE_MARGIN:
        try:
            free = shutil.disk_usage(base).free
        except OSError:
            free = None
        need = int(max(need_bytes, 0)) + FREE_SPACE_MARGIN
        if free is not None and free < need:
            raise UserError(f"not enough free space for the {what} {path}: about {format_bytes(need)} needed "
                            f"(with a margin), {format_bytes(free)} free on {base}; free some space or choose "
                            "another location")
    return real


def format_bytes(n: float) -> str:
    n = float(n)
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1000.0
    return f"{n:.3g} TB"  # pragma: no cover


# --------------------------------------------------------------------------- the atomic write
def _temp_for(real: Path) -> Path:
    real.parent.mkdir(parents=True, exist_ok=True)
    suffix = "".join(real.suffixes[-1:])  # keep the extension: numpy, matplotlib and Blender go by it
    fd, tmp = tempfile.mkstemp(prefix=f".{real.stem[:80]}.", suffix=f"{TEMP_MARK}{suffix}", dir=real.parent)
    os.close(fd)
    return Path(tmp)


def _mode_for(real: Path) -> int:
    try:
        return stat.S_IMODE(os.stat(real).st_mode)  # an existing file keeps its permissions
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def _fsync_path(p: Path) -> None:
    fd = os.open(p, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(d: Path) -> None:
    if os.name != "posix":
        return
    with contextlib.suppress(OSError):
        fd = os.open(d, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_path(path, *, verify: Optional[Callable[[Path], None]] = None, min_size: int = 1,
                expected_size: Optional[int] = None, kind: Optional[str] = None) -> Iterator[Path]:
    """Write ``path`` atomically: the block writes the yielded temporary path; when it ends, the file
    is flushed, checked (at least ``min_size`` bytes, ``expected_size`` if given, :func:`check_file`
    for its extension, then ``verify(tmp)``) and renamed over ``path`` (its real target when ``path``
    is a symbolic link).

    Any failure removes the temporary file and leaves ``path`` as it was; an ``OSError`` becomes a
    :class:`UserError` ``cannot write PATH: CAUSE``.  Other exceptions (Ctrl-C, bugs) propagate.
    """
    shown = os.fspath(path)
    real = output_path(path)
    if real.is_dir():
        raise UserError(f"cannot write {shown}: it is a folder; give a file name")
    tmp = None
    try:
        tmp = _temp_for(real)
        yield tmp
        _fsync_path(tmp)
        size = tmp.stat().st_size
        if size < min_size:
            raise UserError(f"cannot write {shown}: the written file is {size} bytes, expected at least {min_size} "
                            "(the writer failed without saying why; is the disk full?)")
        if expected_size is not None and size != expected_size:
            raise UserError(f"cannot write {shown}: the written file is {size} bytes, expected {expected_size} "
                            "(cut off: is the disk full?)")
        check_file(tmp, kind or real.suffix.lower(), shown=shown)
        if verify is not None:
            verify(tmp)
        os.chmod(tmp, _mode_for(real))
        os.replace(tmp, real)
        tmp = None
        _fsync_dir(real.parent)
    except OSError as exc:
        raise write_error(shown, exc) from None
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def check_file(path: Path, kind: str, shown: Optional[str] = None) -> None:
    """Check that ``path`` is a complete file of ``kind`` (an extension such as ``".npz"``); raises
    :class:`UserError` (a cut-off or unreadable file).  Unknown kinds are only checked for size."""
    shown = shown or str(path)
    kind = kind.lower()
    try:
        if kind == ".npz":
            with zipfile.ZipFile(path) as z:
                bad = z.testzip() if path.stat().st_size <= 32 * 1024 * 1024 else None
                if bad is not None:
                    raise UserError(f"cannot write {shown}: the archive member {bad!r} is damaged (is the disk full?)")
        elif kind == ".json":
            with open(path, "rb") as f:
                json.loads(f.read().decode("utf-8"))
        elif kind == ".png":
            with open(path, "rb") as f:
                head = f.read(8)
                f.seek(max(0, path.stat().st_size - 12))
                tail = f.read(12)
            if head != b"\x89PNG\r\n\x1a\n" or tail[4:8] != b"IEND":
                raise UserError(f"cannot write {shown}: the picture is incomplete (is the disk full?)")
        elif kind == ".blend":
            check_blend(path, shown)
    except zipfile.BadZipFile as exc:
        raise UserError(f"cannot write {shown}: the archive written is not readable ({exc}; is the disk full?)") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot write {shown}: the file written is not valid {kind[1:].upper()} ({exc})") from None


BLEND_MAGIC = b"BLENDER"
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
ZSTD_SEEKABLE_FOOTER = b"\xb1\xea\x92\x8f"
"""Blender writes compressed files as seekable zstd: a seek table whose last 4 bytes are this magic."""
GZIP_MAGIC = b"\x1f\x8b"


def check_blend(path: Path, shown: Optional[str] = None) -> None:
    """A ``.blend`` file starts with ``BLENDER`` and ends with the ``ENDB`` block Blender writes last, or
    (compressed, Blender's default since 4.x) is seekable zstd ending with its seek table's magic;
    anything else is a cut-off file."""
    shown = shown or str(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(16)
        f.seek(max(0, size - 64))
        tail = f.read(64)
    if head.startswith(BLEND_MAGIC):
        if b"ENDB" not in tail:
            raise UserError(f"cannot write {shown}: the .blend file written is cut off (no end block; is the disk "
                            "full?)")
        return
    if head.startswith(ZSTD_MAGIC):
        if not tail.endswith(ZSTD_SEEKABLE_FOOTER):
            raise UserError(f"cannot write {shown}: the compressed .blend file written is cut off (no seek table; "
                            "is the disk full?)")
        return
    if head.startswith(GZIP_MAGIC):
        return  # old gzip compression: the reopen check of the Blender-side writer reads it
    raise UserError(f"cannot write {shown}: the file written is not a .blend file (header {head[:7]!r})")


# --------------------------------------------------------------------------- writers of each kind
def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` atomically to ``path``; returns ``path``."""
    data = bytes(data)
    with atomic_path(path, expected_size=len(data), min_size=min(1, len(data))) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return Path(path)


def write_text(path, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` atomically to ``path`` (``\\n`` line ends kept as they are); returns ``path``."""
    return write_bytes(path, text.encode(encoding))


def json_default(o):
    """``json.dumps(..., default=json_default)``: numpy arrays as lists, numpy scalars as Python numbers, dataclasses
    as dicts, anything else as its ``str`` (paths, enums)."""
    import dataclasses

    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if dataclasses.is_dataclass(o) and not isinstance(o, type):
        return dataclasses.asdict(o)
    return str(o)


def strict_json_default(o):
    """As :func:`json_default` for numpy arrays and scalars; anything else is a ``TypeError`` (a report whose every
    value must be a number, a string or a list of them)."""
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def write_json(path, obj, *, indent: Optional[int] = 2, default=None, allow_nan: bool = True,
               sort_keys: bool = False) -> Path:
    """Write ``obj`` as JSON (a trailing newline) atomically; returns ``path``."""
    text = json.dumps(obj, indent=indent, default=default, allow_nan=allow_nan, sort_keys=sort_keys) + "\n"
    return write_text(path, text)


def save_npz(path, *, compressed: bool = True, **arrays) -> Path:
    """``numpy.savez[_compressed]`` atomically; the archive is reopened and its keys checked."""
    import numpy as np

    names = sorted(arrays)

    def verify(tmp: Path) -> None:
        with zipfile.ZipFile(tmp) as z:
            found = sorted(n[:-4] if n.endswith(".npy") else n for n in z.namelist())
        if found != names:
            raise UserError(f"cannot write {path}: the archive holds {found}, expected {names}")

    from numpy.lib import format as npy_format

    compression = zipfile.ZIP_DEFLATED if compressed else zipfile.ZIP_STORED
    with atomic_path(path, verify=verify, kind=".npz") as tmp:
        # numpy.savez's own layout (one NAME.npy per array, zip64), written with context managers so that a
        # failure (a full disk) closes the archive here instead of in a garbage-collector warning
        with open(tmp, "wb") as f, zipfile.ZipFile(f, mode="w", compression=compression, allowZip64=True) as z:
            for name, value in arrays.items():
                with z.open(f"{name}.npy", "w", force_zip64=True) as member:
                    npy_format.write_array(member, np.asanyarray(value), allow_pickle=False)
    return Path(path)


def save_npy(path, array) -> Path:
    """``numpy.save`` atomically."""
    import numpy as np

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array, allow_pickle=False)
    return Path(path)


def save_figure(fig, path, **kwargs) -> Path:
    """``fig.savefig`` (matplotlib) atomically; the format follows the target's extension."""
    fmt = kwargs.pop("format", None) or (Path(path).suffix[1:].lower() or None)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=fmt, **kwargs)
    return Path(path)


def write_stream(path, writer: Callable[[io.BufferedWriter], None], *, expected_size: Optional[int] = None,
                 verify: Optional[Callable[[Path], None]] = None) -> Path:
    """Write ``path`` atomically with ``writer(binary_file)`` (for formats written piece by piece)."""
    with atomic_path(path, expected_size=expected_size, verify=verify) as tmp:
        with open(tmp, "wb") as f:
            writer(f)
    return Path(path)


def copy_file(src, dst) -> Path:
    """Copy ``src`` to ``dst`` atomically (contents and permission bits)."""
    src = Path(src)
    size = src.stat().st_size
    with atomic_path(dst, expected_size=size, min_size=0) as tmp:
        shutil.copyfile(src, tmp)
    return Path(dst)


# --------------------------------------------------------------------------- one writer at a time
class OutputLock:
    """An exclusive lock on an output for the duration of a run: a lock file
    ``.NAME.unipixie-lock`` beside the (real) target, locked with ``flock`` (``msvcrt`` on Windows)
    and holding the process id.  A second run that tries to lock the same output — in another
    process or the same one — gets a :class:`UserError` naming the first one's process id.  The
    operating system drops the lock when a process dies, so a crashed run never blocks the next.

    Use as a context manager (``with OutputLock(path): ...``) or with :func:`locked`.  ``wait``: seconds to wait
    for the other run to let go before refusing (for short read-modify-write sections such as a benchmark file's
    merge; 0, the default, refuses at once).
    """

    def __init__(self, path, what: str = "output", wait: float = 0.0):
        self.path = Path(os.path.expanduser(os.fspath(path)))
        self.real = output_path(path)
        self.what = what
        self.wait = float(wait)
        self.lock_path = self.real.parent / f".{self.real.name}{LOCK_SUFFIX}"
        self._fd: Optional[int] = None

    def acquire(self) -> "OutputLock":
        if self._fd is not None:
            return self
        try:
            self.real.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise write_error(self.path, exc, f"create the folder of the {self.what}") from None
        import time

        deadline = time.monotonic() + self.wait
        attempts = 0
        while attempts < 20:
            attempts += 1
            try:
                fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError as exc:
                raise UserError(f"cannot write the {self.what} {self.path}: {describe_os_error(exc)}") from None
            if not _try_lock(fd):
                holder = _read_pid(fd)
                os.close(fd)
                if time.monotonic() < deadline:
                    attempts -= 1  # waiting for the holder is not a changing lock file
                    time.sleep(0.05)
                    continue
                who = f" (process {holder})" if holder else ""
                raise UserError(f"the {self.what} {self.path} is being written by another UniPixie run{who}; wait "
                                f"for it to finish or choose another {self.what}")
            try:  # the file may have been removed by its last holder between open and lock: retry
                same = os.path.samestat(os.fstat(fd), os.stat(self.lock_path))
            except OSError:
                same = False
            if same:
                with contextlib.suppress(OSError):
                    os.ftruncate(fd, 0)
                    os.write(fd, str(os.getpid()).encode())
                self._fd = fd
                return self
            _unlock(fd)
            os.close(fd)
        raise UserError(f"cannot lock the {self.what} {self.path}: its lock file {self.lock_path} keeps changing")

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.lock_path)  # while still holding it: a waiting opener re-checks the inode
        _unlock(fd)
        with contextlib.suppress(OSError):
            os.close(fd)

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> bool:
        self.release()
        return False


@contextlib.contextmanager
def locked(paths: Iterable, what: str = "output") -> Iterator[list]:
    """Hold :class:`OutputLock` on every path (in a stable order, so two runs cannot deadlock)."""
    unique = sorted({str(output_path(p)): p for p in paths}.items())
    with contextlib.ExitStack() as stack:
        yield [stack.enter_context(OutputLock(p, what)) for _, p in unique]


def is_temporary(name: str) -> bool:
    """True for the names of :func:`atomic_path`'s temporary files and of lock files (skip them when listing)."""
    return name.startswith(".") and (TEMP_MARK in name or name.endswith(LOCK_SUFFIX))


try:  # POSIX
    import fcntl as _fcntl

    def _try_lock(fd: int) -> bool:
        try:
            _fcntl.flock(fd, _fcntl.LOCK_EX | _fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            return False
        except OSError as exc:  # e.g. a file system without locks: carry on unlocked rather than refuse
            return exc.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS)

    def _unlock(fd: int) -> None:
        with contextlib.suppress(OSError):
            _fcntl.flock(fd, _fcntl.LOCK_UN)
except ImportError:  # pragma: no cover - Windows
    import msvcrt as _msvcrt

    def _try_lock(fd: int) -> bool:
        try:
            os.lseek(fd, 0, os.SEEK_SET)
            _msvcrt.locking(fd, _msvcrt.LK_NBLCK, 1)
            return True
        except OSError:
            return False

    def _unlock(fd: int) -> None:
        with contextlib.suppress(OSError):
            os.lseek(fd, 0, os.SEEK_SET)
            _msvcrt.locking(fd, _msvcrt.LK_UNLCK, 1)


def _read_pid(fd: int) -> Optional[int]:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        text = os.read(fd, 32).decode(errors="replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None
