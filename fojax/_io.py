r"""The one atomic file writer, portable file names and results-folder bookkeeping.

Every file fojax writes goes through `atomic_write` (the `fojax.results` writers, study
results, tuning checkpoints):

- **Atomic.** The bytes go to a temporary file in the destination's directory, are
  flushed to disk (``fsync``), then moved into place (`os.replace`, or a hard link when
  an existing file must not be replaced, so that a concurrent writer cannot be
  clobbered either). A reader sees the old file or the new one, never a part.
- **Permissions like any other program.** The file is created with mode ``0o666`` and
  the user's umask applies (``0o644`` under the usual umask ``022``), not the ``0o600``
  of `tempfile.mkstemp`.
- **Never outside a results folder.** A path built from a results folder (one created
  by `fojax.results.new_results_folder` in this process, i.e. its path is a prefix of
  the destination) must resolve inside that folder: ``folder / "../x.npz"`` or a
  symlinked subfolder pointing elsewhere raise `fojax.errors.UnsafePathError` before anything
  is written.
- **Manifest.** Every file written inside a results folder is recorded, with its
  SHA-256, in the folder's ``fojax-manifest.json`` (`MANIFEST`), rewritten atomically
  after each file. Reopening the folder with ``overwrite=True`` removes the files the
  previous run recorded there (unless changed since), so an overwritten folder holds
  one run's files only, plus whatever the user put there.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import pathlib
import re
import secrets
import threading
from collections.abc import Callable

from ._errors import UnsafePathError


#: The manifest of a results folder: the files the last fojax run wrote in it.
MANIFEST = "fojax-manifest.json"
MANIFEST_FORMAT = "fojax-manifest"

# --------------------------------------------------------------------------- file names

#: Longest name accepted for a config name, observer name or ``--name``.
MAX_NAME_LENGTH = 64
NAME_RULE = (
    f"names become file and folder names, so they may hold only ASCII letters, digits, '.', "
    f"'_' and '-', start with a letter, digit or '_', not end with '.', have at most "
    f"{MAX_NAME_LENGTH} characters and not be a Windows device name (CON, NUL, COM1, ...)"
)
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]*")
_WINDOWS_DEVICES = {"con", "prn", "aux", "nul"} | {f"{d}{i}" for d in ("com", "lpt") for i in range(1, 10)}


def name_problem(name) -> str | None:
    """Why `name` cannot be one file-name component on every common file system, or None.

    The rule (`NAME_RULE`): ASCII letters, digits, ``.``, ``_``, ``-``; first character a
    letter, digit or ``_`` (so no hidden files, no ``..``, nothing that reads as a
    command-line option); no trailing ``.``; at most `MAX_NAME_LENGTH` characters; not a
    Windows device name (``CON``, ``nul.txt``, ...). Path separators are never allowed.
    """
    if not isinstance(name, str):
        return f"it is a {type(name).__name__}, not a string"
    if not name:
        return "it is empty"
    if len(name) > MAX_NAME_LENGTH:
        return f"it has {len(name)} characters (at most {MAX_NAME_LENGTH})"
    if "/" in name or "\\" in name:
        return "it contains a path separator ('/' or '\\')"
    if name[0] in ".-":
        return f"it starts with '{name[0]}'"
    bad = sorted(set(re.sub(r"[A-Za-z0-9._-]", "", name)))
    if bad:
        return f"it contains {', '.join(repr(c) for c in bad)}"
    if not _NAME.fullmatch(name):  # pragma: no cover - covered by the checks above
        return "it is not a portable file name"
    if name.endswith("."):
        return "it ends with '.'"
    if name.split(".", 1)[0].lower() in _WINDOWS_DEVICES:
        return "it is a Windows device name"
    return None


def suggest_name(name, fallback: str = "name") -> str:
    """A valid name close to `name` (invalid characters replaced by ``_``), for messages
    and for names derived from file names."""
    s = re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).lstrip("._-").rstrip(".")[:MAX_NAME_LENGTH].rstrip(".")
    if not s:
        return fallback
    if name_problem(s) is not None:  # a device name: CON -> CON_
        s = s[: MAX_NAME_LENGTH - 1] + "_"
    return s if name_problem(s) is None else fallback


# --------------------------------------------------------------------------- results folders


class _Folder:
    def __init__(self, lexical: pathlib.Path, real: pathlib.Path, manifest: dict):
        self.lexical = lexical
        self.real = real
        self.manifest = manifest


_lock = threading.RLock()
_folders: dict[pathlib.Path, _Folder] = {}


def _absolute(path) -> pathlib.Path:
    """Absolute without normalising ``..`` (unlike `os.path.abspath`)."""
    p = pathlib.Path(path)
    return p if p.is_absolute() else pathlib.Path.cwd() / p


def _real(path: pathlib.Path) -> pathlib.Path:
    """The real location of `path` (its directory resolved; a final symlink is the file
    replaced, not followed)."""
    return path.parent.resolve() / path.name


def _timestamp() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _sha256_file(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_manifest(folder) -> dict | None:
    """The manifest of `folder` (``{"files": {relative path: {"sha256", "bytes"}}, ...}``),
    or None when the folder has none (or an unreadable one)."""
    try:
        m = json.loads((pathlib.Path(folder) / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not (isinstance(m, dict) and m.get("format") == MANIFEST_FORMAT and isinstance(m.get("files"), dict)):
        return None
    return m


def _remove_previous_run(folder: pathlib.Path) -> dict:
    """Delete the files the folder's manifest lists, if unchanged since they were written.
    Returns ``{"removed": [...], "kept_changed": [...]}`` (relative paths)."""
    old = read_manifest(folder)
    removed, kept = [], []
    if old is None:
        return {"removed": removed, "kept_changed": kept, "manifest": False}
    real = folder.resolve()
    for rel, info in sorted(old["files"].items()):
        p = folder / rel
        if pathlib.PurePosixPath(rel).is_absolute() or not _real(_absolute(p)).is_relative_to(real):
            continue  # a manifest edited by hand: never delete outside the folder
        try:
            if not p.is_file() or p.is_symlink():
                continue
            if _sha256_file(p) != (info or {}).get("sha256"):
                kept.append(rel)
                continue
            p.unlink()
            removed.append(rel)
        except OSError:
            kept.append(rel)
    return {"removed": removed, "kept_changed": kept, "manifest": True}


def register_results_folder(folder, *, replace_previous_run: bool = False, continue_run: bool = False) -> dict:
    """Make `folder` a results folder of this process (writes are confined to it and
    recorded in its manifest). With `replace_previous_run`, the files of the previous run
    recorded in its manifest are removed first (those changed since are kept). With
    `continue_run` (``fojax study --resume``), the files already in its manifest stay
    listed and this process's writes are added.

    **Returns:** ``{"removed": [...], "kept_changed": [...], "manifest": bool}``: what was
    done to the previous run's files (``manifest`` False: the folder had no manifest, so
    nothing was removed).
    """
    lexical = _absolute(folder)
    cleanup = {"removed": [], "kept_changed": [], "manifest": False}
    with _lock:
        if replace_previous_run:
            cleanup = _remove_previous_run(lexical)
        manifest = {
            "format": MANIFEST_FORMAT,
            "format_version": 1,
            "note": "files written by the fojax run that created this folder; `--overwrite` "
            "removes these (if unchanged) before writing a new run; other files are never touched",
            "created": _timestamp(),
            "files": {},
        }
        if cleanup["manifest"]:
            manifest["replaced_previous_run"] = {k: cleanup[k] for k in ("removed", "kept_changed")}
        previous = read_manifest(lexical) if continue_run else None
        if previous is not None:
            manifest = {**previous, "continued": [*previous.get("continued", []), _timestamp()]}
        _folders[lexical] = _Folder(lexical, lexical.resolve(), manifest)
        if cleanup["manifest"]:  # the folder's manifest no longer lists removed files
            _write(lexical / MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode("utf-8"), overwrite=True)
    return cleanup


def folder_manifest(folder) -> dict | None:
    """The in-memory manifest of a results folder registered in this process (or None)."""
    f = _folders.get(_absolute(folder))
    return None if f is None else f.manifest


def _owner(path: pathlib.Path) -> _Folder | None:
    """The registered results folder `path` is written into (None: not in one). Raises
    `UnsafePathError` if `path` is built from a results folder but resolves outside it."""
    lexical = _absolute(path)
    real = _real(lexical)
    owner = None
    with _lock:
        folders = list(_folders.values())
    for f in folders:
        if real.is_relative_to(f.real) and real != f.real:
            if owner is None or len(f.real.parts) > len(owner.real.parts):
                owner = f
    for f in folders:
        built_from = lexical.parts[: len(f.lexical.parts)] == f.lexical.parts  # the folder itself too
        if built_from and (owner is None or not owner.real.is_relative_to(f.real)):
            raise UnsafePathError(path, f.lexical, real)
    return owner


def _record(owner: _Folder, path: pathlib.Path, digest: str, size: int) -> None:
    rel = _real(_absolute(path)).relative_to(owner.real).as_posix()
    if rel == MANIFEST:
        return
    with _lock:
        owner.manifest["files"][rel] = {"sha256": digest, "bytes": size}
        text = json.dumps(owner.manifest, indent=1) + "\n"
        _write(owner.real / MANIFEST, text.encode("utf-8"), overwrite=True)


# --------------------------------------------------------------------------- the writer


def _exists_message(path: pathlib.Path) -> str:
    return (
        f"{path} already exists; fojax never overwrites earlier results silently. "
        "Choose another path, delete the file, or pass overwrite=True (CLI: --overwrite)."
    )


_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0) | getattr(os, "O_CLOEXEC", 0)


def _fsync_dir(directory) -> None:
    with contextlib.suppress(OSError, AttributeError):  # not possible on every platform
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _write(path: pathlib.Path, data, *, overwrite: bool, digest: bool = False) -> str | None:
    """Write atomically; returns the SHA-256 of what was written if `digest`."""
    if not overwrite and path.exists():
        raise FileExistsError(_exists_message(path))
    directory = path.parent if str(path.parent) else pathlib.Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(f"directory {directory} does not exist; create it first.")
    while True:
        tmp = directory / f".{path.name[:80]}.{secrets.token_hex(4)}.tmp"
        try:
            fd = os.open(tmp, _FLAGS, 0o666)  # the umask applies, as for any other program
            break
        except FileExistsError:  # pragma: no cover - 32 random bits
            continue
    try:
        with os.fdopen(fd, "wb") as f:
            if callable(data):
                data(f)
            else:
                f.write(data)
            f.flush()
            os.fsync(f.fileno())
        sha = _sha256_file(tmp) if digest else None
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise FileExistsError(_exists_message(path)) from None
            except OSError:  # file systems without hard links: best effort
                if path.exists():
                    raise FileExistsError(_exists_message(path)) from None
                os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
    _fsync_dir(directory)
    return sha


def atomic_write(path, data: bytes | Callable, *, overwrite: bool = False) -> pathlib.Path:
    """Write a file atomically (see the module docstring).

    **Arguments:**

    - `path`: destination file; its directory must exist.
    - `data`: the bytes, or a function ``write(f)`` writing to a binary file object
      (e.g. ``lambda f: np.savez(f, **arrays)``).
    - `overwrite`: replace an existing file. Otherwise an existing file raises
      `FileExistsError` (checked atomically).

    **Returns:** the destination as a `pathlib.Path`.

    **Raises:** `fojax.errors.UnsafePathError` for a path built from a results folder that
    resolves outside it (nothing is written).
    """
    path = pathlib.Path(path)
    owner = _owner(path)
    digest = _write(path, data, overwrite=overwrite, digest=owner is not None)
    if owner is not None:
        _record(owner, path, digest, path.stat().st_size)
    return path
