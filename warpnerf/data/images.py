"""Reading one image file with bounded decoding (:func:`read_image`), and a split's images in
parallel, into one array (:func:`read_all`).

An image file is untrusted input: its header is read first (the format, the size and the number
of frames) and nothing is decoded unless it is a PNG or JPEG of at most :data:`MAX_PIXELS`
pixels; only the first frame of an animated file is decoded. The pixel modes a PNG or JPEG can
hold are converted to RGB(A) as their colours mean (CMYK, palette, grey with alpha ...); a mode
with no such conversion is refused by name."""

from __future__ import annotations

import os
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import UserError
from ..safe_writes import open_input

__all__ = ["read_all", "read_image", "to_uint8", "MAX_PIXELS", "FORMATS"]

PROGRESS_FROM = 20  # a progress bar (on a terminal) from this many images on
MAX_PIXELS = 1 << 27  # pixels of one image (134 M: 16384 x 8192; 1.6 GB as float32 RGB)
FORMATS = ("PNG", "JPEG", "MPO")  # (MPO: the multi-picture JPEG of cameras; its first picture)
# mode -> the mode it is converted to before reading (None: read as it is)
_MODES = {
    "RGB": None, "RGBA": None, "L": None, "LA": None, "I;16": None, "I;16B": None,
    "I;16L": None, "I": "I;16", "1": "L", "La": "LA", "PA": "RGBA", "RGBa": "RGBA",
    "CMYK": "RGB", "YCbCr": "RGB", "HSV": "RGB",
}  # fmt: skip


def read_image(path, where: str = "") -> np.ndarray:
    """The first frame of a PNG or JPEG file as float32 [H, W, 3|4] in [0, 1] (RGB or RGBA; grey
    is repeated to RGB; 8- and 16-bit values divided by 255 and 65535), decoding nothing before
    its header passed the checks: a :class:`UserError` naming ``path`` (and ``where``, e.g.
    "frames[3].file_path in transforms.json") for a file that is not a readable PNG/JPEG, one of
    more than :data:`MAX_PIXELS` pixels, or a pixel mode with no RGB meaning. Colour modes are
    converted as they mean: CMYK (also Adobe's inverted JPEGs) and YCbCr to RGB, palettes to RGB
    (RGBA when the palette has transparency), 1-bit to grey; 16-bit grey stays 16-bit."""
    from PIL import Image

    ctx = f" ({where})" if where else ""
    try:  # (a regular file only: a FIFO or device is refused, never waited on or read)
        fh = open_input(path, "image", follow=True)
    except UserError as e:
        raise UserError(f"{e}{ctx}") from None
    except OSError as e:
        raise UserError(f"{path}: cannot read image{ctx}: {e}") from None
    try:
        with warnings.catch_warnings():  # (the header is checked against MAX_PIXELS below;
            # Pillow's own warning from 89 M pixels would only repeat it, as a Python warning)
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(fh)
        with im:
            _check_header(im, path, ctx)
            im.seek(0)  # (the first frame; nothing beyond it is decoded)
            mode = im.mode
            if mode == "P":
                target = "RGBA" if "transparency" in im.info else "RGB"
            elif mode in _MODES:
                target = _MODES[mode]
            else:
                raise UserError(
                    f"{path}: pixel mode {mode!r} is not supported (RGB, RGBA, grey, grey with "
                    f"alpha, palette, CMYK or 16-bit grey){ctx}"
                )
            im.load()
            img = np.asarray(im.convert(target) if target else im)
    except UserError:
        raise
    except Image.DecompressionBombError:
        raise UserError(_too_large(path, None, ctx)) from None
    except MemoryError:
        raise
    except Exception as e:  # PIL raises many types for corrupt files
        why = str(e).replace(f" {fh!r}", "")  # (PIL names the open file: the path is named)
        raise UserError(f"{path}: cannot read image{ctx}: {why}") from None
    finally:
        fh.close()
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[-1] in (1, 2):  # grey, grey + alpha
        img = np.concatenate([img[..., :1].repeat(3, -1), img[..., 1:]], -1)
    if img.dtype.kind != "u" or img.dtype.itemsize not in (1, 2):  # (no mode above makes one)
        raise UserError(f"{path}: expected 8- or 16-bit pixels, got {img.dtype}{ctx}")
    return img.astype(np.float32) / (255.0 if img.dtype.itemsize == 1 else 65535.0)


def _check_header(im, path, ctx: str) -> None:
    """The format and size of an opened (not yet decoded) image."""
    if im.format not in FORMATS:
        raise UserError(f"{path}: a {im.format or 'unknown'} file; expected PNG or JPEG{ctx}")
    w, h = im.size
    if w * h > MAX_PIXELS:
        raise UserError(_too_large(path, (w, h), ctx))


def _too_large(path, size, ctx: str) -> str:
    got = f"{size[0]}x{size[1]} pixels" if size else "beyond the decoder's own bomb limit"
    return (
        f"{path}: refused: the image declares {got}, more than the limit of {MAX_PIXELS} pixels "
        f"(a decompression bomb or an image far too large to train on){ctx}"
    )


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Values in [0, 1] as 8-bit (x 255, rounded to nearest; 8-bit sources come back exactly,
    composited RGBA within 0.5 / 255)."""
    return np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def read_all(items: list, read_one, check=None, desc: str = "loading images",
             dtype=np.float32) -> np.ndarray:  # fmt: skip
    """``read_one(item) -> float32 [h, w, 3]`` for every item, run in a thread pool (image
    decoding and resampling release the GIL), returned as one [N, h, w, 3] array of ``dtype``
    (float32, or uint8: :func:`to_uint8` of each image as it arrives, a quarter of the memory
    and no float copy of the split) filled as the images arrive in order (no stacked copy of the
    whole split). ``check(j, image)`` runs
    in order on the loading thread before image j is stored (size checks); the first item that
    fails, in order, raises its error, and the images not yet read are cancelled. A progress bar
    shows on a terminal for larger splits."""
    if not items:
        raise ValueError("read_all needs at least one item")
    workers = max(1, min(8, os.cpu_count() or 1, len(items)))
    bar = None
    if len(items) >= PROGRESS_FROM and os.environ.get("RANK", "0") in ("", "0"):  # (rank 0)
        from tqdm import tqdm

        bar = tqdm(total=len(items), desc=desc, unit="img", leave=False, disable=None)
    out = None
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        for j, img in enumerate(pool.map(read_one, items)):
            if check is not None:
                check(j, img)
            if out is None:
                out = np.empty((len(items), *img.shape), dtype=dtype)
            elif img.shape != out.shape[1:]:  # (the loaders' checks name the file first)
                raise ValueError(f"image {j} has shape {img.shape}, expected {out.shape[1:]}")
            out[j] = to_uint8(img) if out.dtype == np.uint8 else img
            if bar is not None:
                bar.update(1)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        if bar is not None:
            bar.close()
    return out
