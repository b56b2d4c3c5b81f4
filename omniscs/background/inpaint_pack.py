"""A compact file of the inpainting network's repair pairs, to train it on another machine (one without the
procedural world's packages, through a transfer limit of 64 MiB): each image whole as WebP of quality 95, its hole
as PNG, and its target (the view without the object) only over the hole's bounding box, the one place the two
differ in what training looks at."""
from __future__ import annotations

import io
import zipfile
from pathlib import Path

import cv2
import numpy as np

from omniscs.errors import OmniscsError, ValidationError
from omniscs.storage import atomic_write_with

PACK_VERSION = 1

#: WebP quality of the packed images (as the depth packs).
IMAGE_QUALITY = 95


def hole_box(hole: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1), exclusive ends, of the hole's pixels."""
    ys, xs = np.nonzero(hole)
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def _webp(image: np.ndarray, what: str) -> bytes:
    ok, buf = cv2.imencode(".webp", np.ascontiguousarray(image[..., ::-1]), [cv2.IMWRITE_WEBP_QUALITY, IMAGE_QUALITY])
    if not ok:
        raise OmniscsError(f"OpenCV could not encode {what} as WebP")
    return buf.tobytes()


def write_pack(path: str | Path, images: np.ndarray, holes: np.ndarray, targets: np.ndarray) -> int:
    """Write pairs to ``path`` (a zip): each image whole, its hole as PNG, and the target only over the hole's
    bounding box (outside it the target is the image: the training loss looks at the hole). Returns the bytes."""
    if (images.dtype != np.uint8 or images.ndim != 4 or holes.shape != images.shape[:3]
            or targets.shape != images.shape or targets.dtype != np.uint8):
        raise OmniscsError("an inpainting pack needs images and targets uint8 [N, H, W, 3] and holes bool [N, H, W]")
    if not holes.reshape(len(holes), -1).any(1).all():
        raise OmniscsError("every pair of an inpainting pack needs a non-empty hole: nothing was written")

    def write(fh) -> None:
        boxes = []
        with zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("version", str(PACK_VERSION))
            for i, (im, hole, target) in enumerate(zip(images, holes, targets)):
                x0, y0, x1, y1 = hole_box(hole)
                boxes.append((x0, y0, x1, y1))
                z.writestr(f"images/{i:06d}.webp", _webp(im, f"image {i}"), compress_type=zipfile.ZIP_STORED)
                z.writestr(f"fills/{i:06d}.webp", _webp(target[y0:y1, x0:x1], f"target {i}"),
                           compress_type=zipfile.ZIP_STORED)
                ok, buf = cv2.imencode(".png", hole.astype(np.uint8) * 255)
                z.writestr(f"holes/{i:06d}.png", buf.tobytes(), compress_type=zipfile.ZIP_STORED)
            arr = io.BytesIO()
            np.savez(arr, boxes=np.array(boxes, np.int32).reshape(-1, 4))
            z.writestr("arrays.npz", arr.getvalue())

    atomic_write_with(Path(path), write)
    return Path(path).stat().st_size


def read_pack(path: str | Path) -> dict[str, np.ndarray]:
    """``images``, ``holes`` and ``targets`` (the image outside the hole's bounding box) from ``write_pack``'s
    file."""
    def decode(z, name: str, flags=cv2.IMREAD_COLOR) -> np.ndarray:
        out = cv2.imdecode(np.frombuffer(z.read(name), np.uint8), flags)
        if out is None:
            raise ValueError(f"{name} does not decode")
        return out[..., ::-1] if out.ndim == 3 else out

    try:
        with zipfile.ZipFile(path) as z:
            if z.read("version").decode() != str(PACK_VERSION):
                raise ValidationError(f"{path} is an inpainting pack of another version")
            with np.load(io.BytesIO(z.read("arrays.npz"))) as a:
                boxes = a["boxes"]
            images, holes, targets = [], [], []
            for i, (x0, y0, x1, y1) in enumerate(boxes):
                im = decode(z, f"images/{i:06d}.webp")
                target = im.copy()
                target[y0:y1, x0:x1] = decode(z, f"fills/{i:06d}.webp")
                images.append(im)
                targets.append(target)
                holes.append(decode(z, f"holes/{i:06d}.png", cv2.IMREAD_GRAYSCALE) > 127)
    except (OSError, KeyError, zipfile.BadZipFile, ValueError) as e:
        raise ValidationError(f"{path} is not a readable inpainting pack ({type(e).__name__}: {e})") from e
    if not images:
        raise ValidationError(f"{path} holds no pairs")
    return {"images": np.ascontiguousarray(np.stack(images)), "holes": np.stack(holes),
            "targets": np.ascontiguousarray(np.stack(targets))}
