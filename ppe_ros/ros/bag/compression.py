"""zstd-compressed messages and storage files, and cut chunks decompressed as far as they go."""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Sequence
from pathlib import Path

from ppe_ros.ros.bag.errors import BagError


def zstd_message(raw: bytes) -> bytes:
    """A zstd-compressed message (``compression_mode: message``) read without its metadata.yaml, decompressed.

    Storage files read directly (a salvaged bag) do not say that their messages are compressed;
    a CDR message never starts with the zstd magic, so these are told apart. A message that does
    not decompress is returned as it is (it is then skipped as undecodable, with the reason).
    """
    try:
        from compression import zstd  # type: ignore[import-not-found]
    except ImportError:
        from backports import zstd  # type: ignore[no-redef]
    try:
        return zstd.decompress(raw)
    except Exception:
        return raw


def partial_decompress(data: bytes, compression: str) -> bytes:
    """As much of a cut chunk's compressed data as decompresses (empty if nothing does).

    ``compression``: an MCAP chunk's ('', 'zstd', 'lz4') or a ROS 1 chunk's ('none', 'bz2', 'lz4').
    """
    try:
        if compression in ('', 'none'):
            return data
        if compression == 'zstd':
            try:
                from compression import zstd  # type: ignore[import-not-found]
            except ImportError:
                from backports import zstd  # type: ignore[no-redef]
            return zstd.ZstdDecompressor().decompress(data)
        if compression == 'bz2':
            import bz2

            return bz2.BZ2Decompressor().decompress(data)
        if compression == 'lz4':
            import lz4.frame

            return lz4.frame.LZ4FrameDecompressor().decompress(data)
    except Exception:
        return b''
    return b''


#: Bytes read from a compressed storage file at a time (small: what decompressed before a corrupt spot is kept).
DECOMPRESS_BLOCK = 1 << 14


def decompress_as_far_as_possible(files: Sequence[Path], stack: contextlib.ExitStack) -> tuple[list[Path], list[str]]:
    """zstd-compressed storage files (``compression_mode: file``) decompressed up to their damage.

    The decompressed files go to a temporary directory removed when ``stack`` closes. Returns
    them and one line per file whose compressed stream is cut or corrupt.
    """
    try:
        from compression import zstd  # type: ignore[import-not-found]
    except ImportError:
        from backports import zstd  # type: ignore[no-redef]

    folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix='process_bag.')))
    out_files, damage = [], []
    for file in files:
        target = folder / file.name.removesuffix('.zstd')
        decompressor = zstd.ZstdDecompressor()
        problem = None
        frames = 0
        in_frame = False
        try:
            with file.open('rb') as source, target.open('wb') as sink:
                while block := source.read(DECOMPRESS_BLOCK):
                    while block:
                        in_frame = True
                        sink.write(decompressor.decompress(block))
                        if not decompressor.eof:
                            break
                        frames += 1
                        in_frame = False
                        block = decompressor.unused_data  # a next zstd frame
                        decompressor = zstd.ZstdDecompressor()
            if in_frame or not frames:
                problem = 'its zstd stream is cut short'
        except zstd.ZstdError as exc:
            problem = f'its zstd stream is corrupt ({exc})'
        except OSError as exc:
            raise BagError(f'cannot decompress {file}: {exc.strerror or exc}') from None
        if problem:
            size = target.stat().st_size
            damage.append(f'{file.name} is damaged: {problem}; {size} bytes decompressed before the damage')
        out_files.append(target)
    return out_files, damage
