"""Lossless PNG frames for the camera channels."""

from __future__ import annotations

import numpy as np

try:  # cv2's PNG codec is ~2-3x faster than PIL's at the same (lossless) output
    import cv2

    cv2.setNumThreads(1)  # one image at a time; threads only add contention in data workers
except ImportError:  # pragma: no cover - cv2 ships with lerobot's deps, PIL is the fallback
    cv2 = None


def encode_png(img: np.ndarray, level: int = 1) -> bytes:
    """Lossless PNG of an RGB uint8 (H, W, 3) image. Level 1 with zlib's RLE strategy: measured on
    128 px rendered-like frames it was both the smallest and among the fastest (0.6 ms encode,
    0.2 ms decode), since deflate's longer match search buys little on rendered scenes."""
    if cv2 is not None:
        params = [cv2.IMWRITE_PNG_COMPRESSION, level, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
        ok, buf = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), params)
        if not ok:
            raise RuntimeError("cv2.imencode failed to encode a PNG")
        return buf.tobytes()
    import io

    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(img).save(out, format="PNG", compress_level=level)
    return out.getvalue()


def decode_png(data: bytes, out: np.ndarray) -> None:
    """Decode a PNG into `out` (H, W, 3) uint8 RGB, checking the size matches."""
    if cv2 is not None:
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if bgr is None:
            raise ValueError("undecodable PNG")
        if bgr.shape != out.shape:
            raise ValueError(f"image is {bgr.shape}, metadata says {out.shape}")
        cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB, dst=out)
        return
    import io

    from PIL import Image

    arr = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    if arr.shape != out.shape:
        raise ValueError(f"image is {arr.shape}, metadata says {out.shape}")
    out[...] = arr
