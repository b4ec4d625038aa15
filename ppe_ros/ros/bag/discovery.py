"""Several inputs: directories of bags expanded, one output bag per input named after it, paths checked."""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

from ppe_ros.ros.bag.errors import BagError
from ppe_ros.ros.bag.output import check_paths, overlaps

#: Storage files that make a directory a rosbag2 (possibly without its metadata.yaml).
STORAGE_PATTERNS = ('*.mcap', '*.db3', '*.mcap.zstd', '*.db3.zstd')
#: Files that are bags on their own (a bare rosbag2 storage file or a ROS 1 bag).
BAG_FILE_SUFFIXES = ('.mcap', '.db3', '.bag')


def is_bag_directory(path: Path) -> bool:
    """Whether ``path`` is one rosbag2 directory: a metadata.yaml or storage files directly in it."""
    return (path / 'metadata.yaml').is_file() or any(next(path.glob(p), None) for p in STORAGE_PATTERNS)


def _bags_in(folder: Path) -> list[Path]:
    """The bags directly in a directory of bags, sorted by name (rosbag2 directories and bag files)."""
    try:
        entries = sorted(folder.iterdir())
    except OSError as exc:
        raise BagError(f'cannot list {folder}: {exc.strerror or exc}') from None
    return [
        entry
        for entry in entries
        if (entry.is_dir() and is_bag_directory(entry)) or (entry.is_file() and entry.suffix in BAG_FILE_SUFFIXES)
    ]


def expand_inputs(paths: Sequence[str | os.PathLike[str]]) -> tuple[list[Path], bool]:
    """The input bags of ``paths`` in order, and whether a directory of bags was among them.

    A rosbag2 directory (see :func:`is_bag_directory`) or a file is one input; any other
    directory stands for the bags directly in it (not deeper). A path that does not exist, or a
    directory holding no bag, stays as it is: opening it says what is wrong.

    Raises:
        BagError: the same bag given twice.
    """
    bags: list[Path] = []
    expanded = False
    for text in paths:
        path = Path(text)
        if path.is_dir() and not is_bag_directory(path):
            inside = _bags_in(path)
            if inside:
                bags.extend(inside)
                expanded = True
                continue
        bags.append(path)
    seen: dict[Path, Path] = {}
    for bag in bags:
        key = bag.resolve()
        if key in seen:
            raise BagError(f'{bag} is given twice (also as {seen[key]})')
        seen[key] = bag
    return bags, expanded


def output_name(path: Path) -> str:
    """The name of an input's output bag: its own name without the storage suffix."""
    path = path.parent if path.name == 'metadata.yaml' else path
    name = path.resolve().name if path.name in ('', '.', '..') else path.name
    for suffix in ('.zstd', *BAG_FILE_SUFFIXES):
        name = name.removesuffix(suffix)
    return name or 'bag'


def output_paths(inputs: Sequence[Path], directory: Path) -> list[Path]:
    """``directory / name`` per input; BagError when two inputs would get the same name."""
    names = [output_name(path) for path in inputs]
    twice = sorted(name for name, count in Counter(names).items() if count > 1)
    if twice:
        clashing = [str(path) for path, name in zip(inputs, names, strict=True) if name in twice]
        raise BagError(f'inputs {clashing} would all write {directory / twice[0]}; give them separately or rename one')
    return [directory / name for name in names]


def check_output_directory(directory: Path, inputs: Sequence[Path], outputs: Sequence[Path], force: bool) -> None:
    """Refuse an OUT directory or an output bag in it that would overwrite an input or an existing path.

    OUT itself may exist (a directory) or is created by the run; each output bag in it follows
    the rules of a single output (:func:`~ppe_ros.ros.bag.output.check_paths`) against every input.

    Raises:
        BagError: with the reason.
    """
    if directory.exists() and not directory.is_dir():
        raise BagError(f'{directory} is not a directory: with several inputs OUT is the directory of their outputs')
    for source in inputs:
        if source.exists() and directory.resolve().is_relative_to(source.resolve()):
            raise BagError(f'refusing to write in {directory}: it is or lies inside the input {source}')
    if not directory.exists():
        parent = directory.resolve().parent
        if not parent.is_dir():
            raise BagError(f'the directory of the output, {parent}, does not exist')
        if not os.access(parent, os.W_OK):
            raise BagError(f'cannot write in {parent}: permission denied')
    for output in outputs:
        for source in inputs:
            if source.exists() and overlaps(source, output):
                raise BagError(f'refusing to write {output}: it is, contains or lies inside the input {source}')
        if directory.exists():
            check_paths(inputs[outputs.index(output)], output, force)
        elif output.exists() or output.is_symlink():  # only a dangling symlink can be here
            raise BagError(f'{output} exists; use --force to replace it')
