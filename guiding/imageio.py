"""Reading and writing images: linear RGB float32 EXR through the OpenEXR package, tone-mapped PNG previews.

Every writer goes through a temporary file in the destination folder and an atomic rename, so an interrupted
run never leaves a file that looks complete.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np
import OpenEXR

from .errors import GuidingError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yields a temporary path beside ``path``; renames it onto ``path`` only if the block succeeds."""
    with atomic_outputs(path) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_outputs(*paths: str | os.PathLike):
    """Yields a temporary path beside each of ``paths`` and renames them onto ``paths`` together once the block
    succeeds. If the block or a rename fails or is interrupted, the files already renamed are removed again: the
    outputs of a run appear all together or not at all."""
    paths = [Path(p) for p in paths]
    temporaries, renamed = [], []
    try:
        for path in paths:
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
            os.close(fd)
            temporaries.append(tmp)
        yield temporaries
        for tmp, path in zip(temporaries, paths):
            os.chmod(tmp, 0o644)  # an ordinary file (mkstemp's 0600 would hide results from other users)
            os.replace(tmp, path)
            renamed.append(path)
    except BaseException:
        for path in renamed:
            path.unlink(missing_ok=True)
        raise
    finally:
        for tmp in temporaries:
            if os.path.exists(tmp):
                os.remove(tmp)


def write_exr(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an (H, W, 3) linear RGB image as float32 EXR."""
    image = np.ascontiguousarray(image[..., :3], dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp, OpenEXR.File(header, {"RGB": image}) as exr:
        exr.write(tmp)


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an RGB EXR as an (H, W, 3) float32 array; a missing, corrupt or non-RGB file is a GuidingError."""
    if os.path.isdir(path):
        raise GuidingError(f"cannot read image '{path}': it is a folder")
    if not os.path.isfile(path):
        raise GuidingError(f"cannot read image '{path}': no such file")
    try:
        with OpenEXR.File(str(path)) as exr:
            channels = exr.channels()
            if "RGB" in channels:
                pixels = channels["RGB"].pixels
            elif {"R", "G", "B"} <= channels.keys():
                pixels = np.stack([channels[c].pixels for c in "RGB"], axis=-1)
            else:
                raise GuidingError(f"cannot read image '{path}': no RGB channels (found {', '.join(channels)})")
            pixels = np.array(pixels, dtype=np.float32)
    except GuidingError:
        raise
    except Exception as error:  # OpenEXR reports corrupt and truncated files as RuntimeError or ValueError
        raise GuidingError(f"cannot read image '{path}': not a readable EXR file ({error})") from None
    if pixels.ndim != 3 or pixels.shape[2] < 3:
        raise GuidingError(f"cannot read image '{path}': expected an RGB image, got shape {pixels.shape}")
    return pixels[..., :3]


def to_srgb8(image: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear RGB → 8-bit sRGB (clipped); non-finite pixels show as magenta so they cannot go unnoticed."""
    linear = np.nan_to_num(image[..., :3] * exposure, nan=0.0, posinf=0.0, neginf=0.0)
    linear = np.clip(linear, 0.0, 1.0)
    srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)
    out = np.round(srgb * 255).astype(np.uint8)
    out[~np.isfinite(image[..., :3]).all(axis=-1)] = (255, 0, 255)
    return out


def write_png(path: str | os.PathLike, image: np.ndarray, exposure: float = 1.0) -> None:
    """Write a tone-mapped sRGB preview of a linear image."""
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(to_srgb8(image, exposure)).save(tmp, format="PNG")


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` (its folder made if needed) all at once: a reader sees the old file or the new."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)
