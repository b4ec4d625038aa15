"""The output rosbag2 (staged, then renamed) and the checks that keep the input safe."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import StoragePlugin, Writer

from ppe_ros.ros.bag.errors import BagError

STORAGES: dict[str, StoragePlugin] = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
DEFAULT_STORAGE = 'mcap'
#: rosbag2 format version of the output (Jazzy's).
OUTPUT_BAG_VERSION = 9


class OutputBag:
    """The output rosbag2, written in a staging directory next to OUT and renamed when closed."""

    def __init__(self, final: Path, storage: str, force: bool) -> None:
        self.final = final
        self.storage = storage
        self.force = force
        self.staging = Path(tempfile.mkdtemp(prefix=f'.{final.name}.', suffix='.partial', dir=final.parent))
        self.path = self.staging / final.name
        self.writer = Writer(self.path, version=OUTPUT_BAG_VERSION, storage_plugin=STORAGES[storage])
        self.written = 0
        self._typestore: Any = None
        try:
            self.writer.open()
        except BaseException:
            shutil.rmtree(self.staging, ignore_errors=True)
            raise

    def add_connection(self, topic: str, msgtype: str, typestore: Any) -> Any:
        return self.writer.add_connection(topic, msgtype, typestore=typestore)

    def write(self, connection: Any, timestamp: int, data: bytes) -> None:
        self.writer.write(connection, timestamp, data)
        self.written += 1

    def close(self) -> None:
        """Write the index and metadata.yaml; on failure the staging directory is kept as it is."""
        self.writer.close()

    def publish(self) -> Path:
        """Move the closed bag to OUT (replacing it only with ``force``) and remove the staging directory."""
        old = None
        if self.final.exists() or self.final.is_symlink():
            if not self.force:
                raise FileExistsError(f'{self.final} appeared while processing; the output is left in {self.path}')
            old = self.staging / f'{self.final.name}.replaced'
            os.rename(self.final, old)
        os.rename(self.path, self.final)
        if old is not None:
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old)
            else:
                old.unlink()
        self.staging.rmdir()
        return self.final

    def discard(self) -> None:
        shutil.rmtree(self.staging, ignore_errors=True)


def _files_of(path: Path) -> list[Path]:
    """``path`` and, for a directory, the files and directories in it (not deeper: a bag is flat)."""
    if path.is_dir():
        with contextlib.suppress(OSError):
            return [path, *path.iterdir()]
    return [path]


def _shares_a_file(input_path: Path, output_path: Path) -> bool:
    """Whether OUT is (by device and inode: a hard link too) the input, one of its files, or holds one."""
    if not output_path.exists():
        return False
    for source in _files_of(input_path):
        for target in _files_of(output_path):
            with contextlib.suppress(OSError):
                if os.path.samefile(source, target):
                    return True
    return False


def overlaps(input_path: Path, output_path: Path) -> bool:
    """Whether writing ``output_path`` could touch the input: it is, holds or lies inside it, or shares a file."""
    source = input_path.resolve()
    target = output_path.resolve()
    return (
        target == source
        or source.is_relative_to(target)
        or target.is_relative_to(source)
        or _shares_a_file(input_path, output_path)
    )


def check_paths(input_path: Path, output_path: Path, force: bool) -> None:
    """Refuse outputs that would overwrite the input or an existing path without ``force``.

    Raises:
        BagError: with the reason.
    """
    target = output_path.resolve()
    if overlaps(input_path, output_path):
        raise BagError(f'refusing to write {output_path}: it is, contains or lies inside the input {input_path}')
    if output_path.exists() or output_path.is_symlink():
        if not force:
            raise BagError(f'{output_path} exists; use --force to replace it')
    if not target.parent.is_dir():
        raise BagError(f'the directory of the output, {target.parent}, does not exist')
    if not os.access(target.parent, os.W_OK):
        raise BagError(f'cannot write in {target.parent}: permission denied')
