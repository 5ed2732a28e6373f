"""Reading and writing images: linear RGB float32 EXR through the OpenEXR package, tone-mapped PNG previews.

Every writer goes through a temporary file in the destination folder and an atomic rename, so an interrupted
run never leaves a file that looks complete.
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import json
import os
import secrets
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenEXR

from guiding import strict_json
from guiding.errors import GuidingError


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
            # Listed before it exists: a Ctrl-C between its creation and its listing (mkstemp's) left it behind.
            tmp = str(path.parent / f".{path.name}.{secrets.token_hex(8)}.tmp{path.suffix}")
            temporaries.append(tmp)
            open(tmp, "x").close()
        yield temporaries
        for tmp, path in zip(temporaries, paths):
            os.chmod(tmp, 0o644)  # an ordinary file, readable by other users whatever the umask
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


#: Prefix of the header attributes this package writes (``guiding/method``, ``guiding/spp``, ...).
METADATA_PREFIX = "guiding/"


def _attribute(value):
    """A metadata value as an EXR header attribute: numbers and strings as they are, anything else as strict JSON."""
    if isinstance(value, (int, float, str)) and not isinstance(value, bool):
        return value
    return strict_json.dumps(value, indent=None)


def write_exr(path: str | os.PathLike, image: np.ndarray, metadata: dict | None = None) -> None:
    """Write an (H, W, 3) linear RGB image as float32 EXR, with ``metadata`` (name → value; what made the image)
    as header attributes ``guiding/NAME`` (:func:`read_exr_metadata` reads them back)."""
    image = np.ascontiguousarray(image[..., :3], dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              **{METADATA_PREFIX + name: _attribute(value) for name, value in (metadata or {}).items()}}
    with atomic_path(path) as tmp, OpenEXR.File(header, {"RGB": image}) as exr:
        exr.write(tmp)


class _NativeOutput:
    """Captures what OpenEXR prints inside a ``with`` block: its C++ core writes to the process's stdout and stderr
    (file descriptors 1 and 2), its Python binding to ``sys.stdout``; the text is in :attr:`text` afterwards. A
    corrupt file otherwise makes OpenEXR print its own lines around the one error line of the command line."""

    def __enter__(self):
        sys.stdout.flush()
        sys.stderr.flush()
        self.python = io.StringIO()
        self.redirects = contextlib.ExitStack()
        self.redirects.enter_context(contextlib.redirect_stdout(self.python))
        self.redirects.enter_context(contextlib.redirect_stderr(self.python))
        self.sink = tempfile.TemporaryFile()
        self.saved = [os.dup(1), os.dup(2)]
        for fd in (1, 2):
            os.dup2(self.sink.fileno(), fd)
        return self

    def __exit__(self, *exc_info):
        ctypes.CDLL(None).fflush(None)   # what C stdio still buffers goes to the sink, not to the terminal later
        for fd, saved in zip((1, 2), self.saved):
            os.dup2(saved, fd)
            os.close(saved)
        self.redirects.close()
        self.sink.seek(0)
        self.text = self.sink.read().decode(errors="replace") + self.python.getvalue()
        self.sink.close()
        return False


def _exr_problem(path: str | os.PathLike, error: Exception | None, native: str) -> str:
    """Why ``path`` could not be read, in a few words, from OpenEXR's exception and what its core printed."""
    for line in native.splitlines():
        if "EXR_ERR_" in line:   # "PATH: (EXR_ERR_BAD_CHUNK_LEADER) Preparing to read scanline 48 ..., found ..."
            code, _, what = line.removeprefix(f"{path}: ").strip().partition(") ")
            return f"not a readable EXR file: truncated or corrupt ({code.strip('(')}: {what})"
    if error is not None and "Unable to open" in str(error):
        return "not a readable EXR file (no EXR file, or its header is truncated or corrupt)"
    return f"not a readable EXR file: truncated or corrupt ({error or native.strip().splitlines()[0]})"


def _read(path: str | os.PathLike, header_only: bool = False) -> tuple[dict, list[str], np.ndarray | None]:
    """(header, channel names, RGB pixels as float32 or None without RGB channels) of EXR file ``path``; a
    GuidingError of one line when OpenEXR reports a problem."""
    header, names, pixels, error = {}, [], None, None
    with _NativeOutput() as native:
        try:
            with OpenEXR.File(str(path), header_only=header_only) as exr:
                header = dict(exr.header())   # a copy: the File empties its own when it closes
                channels = {} if header_only else exr.channels()
                names = list(channels)
                if "RGB" in channels:
                    pixels = np.array(channels["RGB"].pixels, dtype=np.float32)
                elif {"R", "G", "B"} <= channels.keys():
                    pixels = np.stack([channels[c].pixels for c in "RGB"], axis=-1).astype(np.float32)
        except Exception as caught:  # noqa: BLE001 - OpenEXR reports bad files as RuntimeError or ValueError
            error = caught
    # What OpenEXR's core printed counts even when it returned pixels: they may be partly missing.
    if error is not None or "EXR_ERR_" in native.text or "Exception" in native.text:
        raise GuidingError(f"cannot read image '{path}': {_exr_problem(path, error, native.text)}")
    return header, names, pixels


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an RGB EXR as an (H, W, 3) float32 array; a missing, truncated, corrupt or non-RGB file is a
    GuidingError of one line (OpenEXR's own messages are captured, not printed)."""
    if os.path.isdir(path):
        raise GuidingError(f"cannot read image '{path}': it is a folder")
    if not os.path.isfile(path):
        raise GuidingError(f"cannot read image '{path}': no such file")
    _, channels, pixels = _read(path)
    if pixels is None:
        raise GuidingError(f"cannot read image '{path}': no RGB channels (found {', '.join(channels) or 'none'})")
    if pixels.ndim != 3 or pixels.shape[2] < 3:
        raise GuidingError(f"cannot read image '{path}': expected an RGB image, got shape {pixels.shape}")
    return pixels[..., :3]


def read_exr_metadata(path: str | os.PathLike) -> dict:
    """The ``guiding/...`` header attributes of an EXR written by :func:`write_exr` (prefix removed; values
    written as JSON are decoded)."""
    header, _, _ = _read(path, header_only=True)
    metadata = {}
    for name, value in header.items():
        if name.startswith(METADATA_PREFIX):
            if isinstance(value, str) and value[:1] in "{[":
                value = json.loads(value)
            metadata[name[len(METADATA_PREFIX):]] = value
    return metadata


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
