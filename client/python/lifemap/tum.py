"""Frames of a TUM RGB-D folder (rgb.txt, depth.txt, optional groundtruth.txt), as lifemap.Frame.

Decoding the PNGs needs Pillow (Debian python3-pil); the client itself does not.
TUM depth is uint16 at 5000 units per metre; the fr1 camera's intrinsics are the default here.
"""
from __future__ import annotations

import bisect
from pathlib import Path
from typing import Iterator, List, Optional, Tuple

import numpy as np

from lifemap.client import Frame, Intrinsics

FR1_INTRINSICS: Intrinsics = (517.3, 516.5, 318.6, 255.3)
TUM_DEPTH_SCALE = 5000.0
_MAX_GAP_S = 0.02  # colour, depth and ground truth closer than this belong together


def _list(path: Path) -> List[Tuple[float, List[str]]]:
    rows = []
    with open(path) as f:
        for number, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.split()
            try:
                rows.append((float(fields[0]), fields[1:]))
            except ValueError:
                raise ValueError(f"{path}:{number}: expected 'timestamp ...', got {line!r}") from None
    rows.sort(key=lambda r: r[0])
    return rows


def _nearest(rows, times, t: float):
    i = bisect.bisect_left(times, t)
    best = min((j for j in (i - 1, i) if 0 <= j < len(rows)), key=lambda j: abs(times[j] - t),
               default=None)
    if best is None or abs(times[best] - t) > _MAX_GAP_S:
        return None
    return rows[best]


def frames(folder, *, intrinsics: Intrinsics = FR1_INTRINSICS, groundtruth: bool = False,
           max_frames: Optional[int] = None, stride: int = 1) -> Iterator[Frame]:
    """The folder's colour frames with the depth (and, with groundtruth, the pose) nearest in
    time, each within 20 ms; frames without one are skipped. Timestamps are the recording's."""
    try:
        from PIL import Image
    except ImportError:
        raise ImportError("lifemap.tum decodes PNGs with Pillow: apt install python3-pil") from None
    folder = Path(folder)
    for name in ("rgb.txt", "depth.txt"):
        if not (folder / name).is_file():
            raise FileNotFoundError(f"{folder} is not a TUM RGB-D folder: no {name}")
    depth = _list(folder / "depth.txt")
    depth_times = [t for t, _ in depth]
    truth, truth_times = [], []
    if groundtruth:
        if not (folder / "groundtruth.txt").is_file():
            raise FileNotFoundError(f"{folder} has no groundtruth.txt")
        truth = _list(folder / "groundtruth.txt")
        truth_times = [t for t, _ in truth]
    sent = 0
    for index, (t, fields) in enumerate(_list(folder / "rgb.txt")):
        if index % stride:
            continue
        d = _nearest(depth, depth_times, t)
        pose = None
        if groundtruth:
            g = _nearest(truth, truth_times, t)
            if g is None:
                continue
            pose = tuple(float(v) for v in g[1][:7])
        if d is None:
            continue
        color = np.asarray(Image.open(folder / fields[0]).convert("RGB"))
        depth_image = np.asarray(Image.open(folder / d[1][0])).astype(np.uint16)
        yield Frame(color=color, depth=depth_image, intrinsics=intrinsics,
                    depth_scale=TUM_DEPTH_SCALE, pose=pose, timestamp_s=t)
        sent += 1
        if max_frames is not None and sent >= max_frames:
            return
