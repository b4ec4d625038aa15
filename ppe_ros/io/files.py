"""Safe output files: written atomically, never over an input (same device and inode).

* :func:`write_files_atomically` writes each file to a temporary file in the target's own folder
  (``.NAME.<random>.tmp``) and renames it into place with :func:`os.replace` only after every file of
  the set has been written completely. A failure (full disk, interruption) removes the temporary files
  and leaves every target as it was: there is never a truncated output under the final name.
* :func:`same_file` compares files by device and inode (:func:`os.path.samefile`), so a hard link or a
  symbolic link to an input counts as the input; :func:`refuse_overwriting_inputs` raises for any output
  that is one of the inputs or that two outputs share.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import BinaryIO

#: A writer fills one open binary stream with a file's content.
Writer = Callable[[BinaryIO], None]


def same_file(first: str | os.PathLike[str], second: str | os.PathLike[str]) -> bool:
    """True if both names are the same file (same device and inode; hard and symbolic links count).

    Two names of which one does not exist are the same file only if they resolve to the same path
    (then writing one would create the other).
    """
    try:
        return os.path.samefile(first, second)
    except OSError:
        return Path(first).resolve() == Path(second).resolve()


def refuse_overwriting_inputs(
    outputs: Sequence[str | os.PathLike[str]], inputs: Iterable[str | os.PathLike[str]]
) -> None:
    """Raise ValueError if an output is an input (by device and inode) or two outputs are one file."""
    input_list = [Path(p) for p in inputs]
    output_list = [Path(p) for p in outputs]
    for index, out in enumerate(output_list):
        for source in input_list:
            if same_file(out, source):
                link = '' if out.resolve() == source.resolve() else ' (a link to it)'
                raise ValueError(f'refusing to overwrite the input {source} with the output {out}{link}')
        for other in output_list[:index]:
            if same_file(out, other):
                raise ValueError(f'two outputs would be written to the same file: {other} and {out}')


def check_output_targets(paths: Sequence[str | os.PathLike[str]], *, overwrite: bool = False) -> None:
    """Raise before anything is written if an output cannot be created.

    Raises:
        FileNotFoundError: an output folder does not exist.
        FileExistsError: an output exists and ``overwrite`` is False.
    """
    for target in map(Path, paths):
        folder = target.parent
        if not folder.is_dir():
            raise FileNotFoundError(f'output folder {folder} does not exist (for {target.name})')
        if not overwrite and (target.exists() or target.is_symlink()):
            raise FileExistsError(f'{target} exists (use --force to replace it)')


def _open_for_writing(path: Path) -> BinaryIO:
    """A new file opened for binary writing (fails if it exists; permissions from the umask)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    return os.fdopen(fd, 'wb')


def write_files_atomically(
    files: Sequence[tuple[str | os.PathLike[str], Writer]], *, overwrite: bool = False
) -> list[Path]:
    """Write several files all-or-nothing: every file complete under its name, or none changed.

    Args:
        files: ``(path, writer)`` pairs; ``writer(stream)`` writes the whole content.
        overwrite: replace existing files (else an existing target raises before anything is written).

    Returns:
        The paths written.

    Raises:
        FileExistsError: a target exists and ``overwrite`` is False (nothing written).
        FileNotFoundError: a target's folder does not exist (nothing written).
        OSError: writing failed (e.g. ENOSPC); every temporary file is removed, no target changed.
    """
    targets = [Path(path) for path, _ in files]
    check_output_targets(targets, overwrite=overwrite)
    temporaries: list[Path] = []
    try:
        for target, (_, writer) in zip(targets, files, strict=True):
            temporary = target.with_name(f'.{target.name}.{secrets.token_hex(4)}.tmp')
            try:
                with _open_for_writing(temporary) as stream:
                    temporaries.append(temporary)
                    writer(stream)
                    stream.flush()
                    os.fsync(stream.fileno())
            except OSError as exc:  # say which output (the stream's error names no file)
                raise OSError(exc.errno, f'cannot write {target}: {exc.strerror or exc}') from None
        for temporary, target in zip(temporaries, targets, strict=True):
            os.replace(temporary, target)
    except BaseException:
        for temporary in temporaries:
            try:
                temporary.unlink()
            except FileNotFoundError:
                pass
        raise
    return targets


def write_file_atomically(path: str | os.PathLike[str], writer: Writer, *, overwrite: bool = False) -> Path:
    """:func:`write_files_atomically` for one file."""
    return write_files_atomically([(path, writer)], overwrite=overwrite)[0]
