"""A compact file of the relative-depth network's training arrays, to train it on another machine (one without
the procedural world's packages, through a transfer limit of 64 MiB): images as WebP of quality 95 (a mean absolute
error of about 2.5 of 255 levels on procedural renders, below the training augmentation's pixel noise; lossless PNG
made the pack 3.5 times larger), inverse depth as float16 (relative precision 5e-4, far below the SSI loss's
residuals), compressed; read back as the arrays ``train_depth_net`` takes."""
from __future__ import annotations

import io
import zipfile
from pathlib import Path

import cv2
import numpy as np

from omniscs.errors import OmniscsError, ValidationError
from omniscs.storage import atomic_write_with

PACK_VERSION = 1

#: WebP quality of the packed images.
IMAGE_QUALITY = 95


def write_pack(path: str | Path, images: np.ndarray, inv_depths: np.ndarray, repair: np.ndarray) -> int:
    """Write the arrays (``make_training_data``'s) to ``path`` (a zip); returns its size in bytes."""
    if images.dtype != np.uint8 or images.ndim != 4 or inv_depths.shape != images.shape[:3] or len(repair) != len(images):
        raise OmniscsError("a depth pack needs images uint8 [N, H, W, 3], inverse depths [N, H, W] and repair [N]")
    if not np.isfinite(inv_depths).all():
        raise OmniscsError("the inverse depths hold NaN or Inf: nothing was written")

    def write(fh) -> None:
        with zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("version", str(PACK_VERSION))
            for i, im in enumerate(images):
                ok, buf = cv2.imencode(".webp", np.ascontiguousarray(im[..., ::-1]),
                                       [cv2.IMWRITE_WEBP_QUALITY, IMAGE_QUALITY])
                if not ok:
                    raise OmniscsError(f"OpenCV could not encode training image {i} as WebP")
                z.writestr(f"images/{i:06d}.webp", buf.tobytes(), compress_type=zipfile.ZIP_STORED)
            arr = io.BytesIO()
            np.savez(arr, inv_depths=inv_depths.astype(np.float16), repair=np.asarray(repair, bool))
            z.writestr("arrays.npz", arr.getvalue())

    atomic_write_with(Path(path), write)
    return Path(path).stat().st_size


def read_pack(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(images uint8 [N, H, W, 3], inverse depths float32 [N, H, W], repair bool [N]) from ``write_pack``'s file."""
    try:
        with zipfile.ZipFile(path) as z:
            if z.read("version").decode() != str(PACK_VERSION):
                raise ValidationError(f"{path} is a depth pack of another version")
            with np.load(io.BytesIO(z.read("arrays.npz"))) as a:
                inv, repair = a["inv_depths"].astype(np.float32), a["repair"]
            names = sorted(n for n in z.namelist() if n.startswith("images/"))
            images = np.stack([cv2.imdecode(np.frombuffer(z.read(n), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
                               for n in names])
    except (OSError, KeyError, zipfile.BadZipFile, ValueError) as e:
        raise ValidationError(f"{path} is not a readable depth pack ({type(e).__name__}: {e})") from e
    if images.shape[:3] != inv.shape or len(repair) != len(images):
        raise ValidationError(f"{path}: {len(images)} images but {len(inv)} depth maps")
    return np.ascontiguousarray(images), inv, repair
