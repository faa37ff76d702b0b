"""The key-object map model: for each trajectory key point ``l`` and camera direction ``d``, a cloud
of key objects ``{(x, y, z, F, H)}`` (3D position, the detector that found it, its descriptor),
held relative to a base viewpoint ``r_B = argmax_r sum_d N(l, d, r)``: the viewpoint that sees
the most key objects over all directions.

Viewpoint frame: metres from the viewpoint's camera centre, x along its image right, y along
its image up (forward), z up. Directions are names ("nadir", "front", ...), so a multi-camera
rig adds its own; detectors are names too ("gradient", "extremum", "line", "region" or a
feature backend's name for triangulated landmarks).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from orthonav.atomic import write_npz_atomic
from orthonav.errors import OrthonavError

LOW_LEVEL = ("gradient", "extremum")
HIGH_LEVEL = ("line", "region")


@dataclass
class KeyObjectCloud:
    """Key objects of one (key point, direction, viewpoint).

    ``xyz`` (N, 3) metres in the base viewpoint's frame; ``detectors`` the name F of each;
    ``descriptors`` one array H each; ``region`` the index (in this cloud) of the region object
    the object lies in, -1 if none; ``ends`` (N, 2, 3) a line's two endpoints, NaN for others.
    """

    xyz: np.ndarray
    detectors: list[str]
    descriptors: list[np.ndarray]
    region: np.ndarray | None = None
    ends: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, float).reshape(-1, 3)
        n = len(self.xyz)
        if not n == len(self.detectors) == len(self.descriptors):
            raise OrthonavError(
                f"key object cloud: {n} positions, {len(self.detectors)} detectors and "
                f"{len(self.descriptors)} descriptors; expected one of each per key object"
            )
        if any(not isinstance(name, str) or not name for name in self.detectors):
            raise OrthonavError("key object cloud: every detector name F must be a non-empty string")
        self.region = np.full(n, -1, np.int64) if self.region is None else np.asarray(self.region, np.int64)
        self.ends = np.full((n, 2, 3), np.nan) if self.ends is None else np.asarray(self.ends, float)
        if self.region.shape != (n,) or self.ends.shape != (n, 2, 3):
            raise OrthonavError(
                f"key object cloud: region {self.region.shape} and ends {self.ends.shape}; "
                f"expected ({n},) and ({n}, 2, 3)"
            )

    def __len__(self) -> int:
        return len(self.xyz)

    def counts(self) -> dict[str, int]:
        names, counts = np.unique(np.array(self.detectors, dtype=object).astype(str), return_counts=True)
        return {str(k): int(v) for k, v in zip(names, counts, strict=True)}

    def select(self, detector: str) -> np.ndarray:
        """Indices of the objects found by ``detector``."""
        return np.flatnonzero(np.array(self.detectors, dtype=object) == detector)

    def subset(self, keep: np.ndarray) -> KeyObjectCloud:
        """The objects where ``keep`` (bool) holds; region links renumbered, dropped ones -1."""
        keep = np.asarray(keep, bool)
        new_index = np.cumsum(keep) - 1
        region = np.where(self.region >= 0, new_index[np.maximum(self.region, 0)], -1)
        region = np.where((self.region >= 0) & keep[np.maximum(self.region, 0)], region, -1)
        idx = np.flatnonzero(keep)
        return KeyObjectCloud(
            self.xyz[idx],
            [self.detectors[i] for i in idx],
            [self.descriptors[i] for i in idx],
            region[idx],
            self.ends[idx],
        )

    def moved(self, pose: np.ndarray) -> KeyObjectCloud:
        """This cloud, given in a viewpoint placed at ``pose`` (x, y, z, yaw_deg) of another frame,
        expressed in that other frame."""
        ends = self.ends.reshape(-1, 3)
        return KeyObjectCloud(
            place(self.xyz, pose),
            list(self.detectors),
            list(self.descriptors),
            self.region.copy(),
            place(ends, pose).reshape(-1, 2, 3),
        )


def place(xyz: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Points of a viewpoint frame into a frame where that viewpoint sits at ``pose``
    (x, y, z, yaw_deg; yaw clockwise from that frame's y axis)."""
    yaw = math.radians(float(pose[3]))
    c, s = math.cos(yaw), math.sin(yaw)
    right, forward = xyz[:, 0], xyz[:, 1]
    return np.column_stack(
        [pose[0] + right * c + forward * s, pose[1] - right * s + forward * c, pose[2] + xyz[:, 2]]
    )


def relative_pose(pose: np.ndarray, base: np.ndarray) -> np.ndarray:
    """``pose`` (x, y, z, yaw_deg in a common frame) as seen from the viewpoint at ``base``."""
    yaw = math.radians(float(base[3]))
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = pose[0] - base[0], pose[1] - base[1]
    turn = (float(pose[3]) - float(base[3]) + 180.0) % 360.0 - 180.0
    return np.array([dx * c - dy * s, dx * s + dy * c, pose[2] - base[2], turn])


@dataclass
class KeyObjectMap:
    """Clouds keyed by (key point l, direction d, viewpoint r), each relative to r_B(l).

    ``poses[(l, r)]``: viewpoint r in r_B(l)'s frame (x, y, z, yaw_deg); ``origins[l]``: r_B(l)
    in a common frame (a VO run's local frame), which links the key points to each other.
    """

    clouds: dict[tuple[int, str, int], KeyObjectCloud] = field(default_factory=dict)
    poses: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    origins: dict[int, np.ndarray] = field(default_factory=dict)
    names: dict[int, str] = field(default_factory=dict)  # key point -> its keyframe photo

    def add(self, key_point: int, direction: str, viewpoint: int, cloud: KeyObjectCloud) -> None:
        self.clouds[(key_point, direction, viewpoint)] = cloud

    @property
    def key_points(self) -> list[int]:
        return sorted({point for point, _, _ in self.clouds})

    def counts(self, key_point: int) -> dict[int, int]:
        """N(l, r) = sum over directions of the key objects each viewpoint sees."""
        totals: dict[int, int] = {}
        for (point, _, r), cloud in self.clouds.items():
            if point == key_point:
                totals[r] = totals.get(r, 0) + len(cloud)
        return totals

    def base_viewpoint(self, key_point: int) -> int:
        """r_B of a trajectory key point: the viewpoint with the most key objects, all directions summed."""
        totals = self.counts(key_point)
        if not totals:
            raise OrthonavError(f"key object map: no clouds at trajectory key point {key_point}")
        return max(sorted(totals), key=lambda r: totals[r])

    def base_clouds(self, key_point: int) -> dict[str, KeyObjectCloud]:
        """The base viewpoint's cloud of each direction at ``key_point``."""
        base = self.base_viewpoint(key_point)
        return {d: c for (point, d, r), c in self.clouds.items() if point == key_point and r == base}

    def reidentify(
        self, first: int, second: int, detector: str, direction: str, ratio: float = 0.8
    ) -> tuple[np.ndarray, np.ndarray]:
        """Objects of key point ``first``'s base cloud found again in ``second``'s by descriptor
        (nearest neighbour, ratio test): (K, 2) index pairs and (K, 3) offsets (m) between the
        two positions once ``first``'s are moved into ``second``'s base frame via the origins."""
        one, two = self.base_clouds(first).get(direction), self.base_clouds(second).get(direction)
        empty = np.zeros((0, 2), np.int64), np.zeros((0, 3))
        if one is None or two is None:
            return empty
        i1, i2 = one.select(detector), two.select(detector)
        if len(i1) < 2 or len(i2) < 2:
            return empty
        d1, d2 = np.stack([one.descriptors[i] for i in i1]), np.stack([two.descriptors[i] for i in i2])
        binary = d1.dtype == np.uint8
        if not binary:
            d1, d2 = d1.astype(np.float32), d2.astype(np.float32)
        knn = cv2.BFMatcher(cv2.NORM_HAMMING if binary else cv2.NORM_L2).knnMatch(d1, d2, k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
        pairs = np.array([(i1[m.queryIdx], i2[m.trainIdx]) for m in good], np.int64).reshape(-1, 2)
        shift = relative_pose(self.origins[first], self.origins[second])
        moved = place(one.xyz[pairs[:, 0]], shift)
        return pairs, moved - two.xyz[pairs[:, 1]]

    def summary(self) -> dict:
        """Per key point: its photo, base viewpoint, and counts per viewpoint, direction, detector."""
        out = []
        for point in self.key_points:
            views = {}
            for (p, d, r), cloud in sorted(self.clouds.items()):
                if p == point:
                    views.setdefault(str(r), {})[d] = cloud.counts()
            out.append(
                {
                    "key_point": point,
                    "photo": self.names.get(point, ""),
                    "base_viewpoint": self.base_viewpoint(point),
                    "objects_per_viewpoint": {str(r): n for r, n in sorted(self.counts(point).items())},
                    "viewpoints": views,
                    "origin": self.origins[point].tolist() if point in self.origins else None,
                }
            )
        return {"key_points": out, "objects": sum(len(c) for c in self.clouds.values())}

    def save(self, path: str | Path) -> None:
        """One compressed ``.npz`` (written atomically): flat per-object arrays and one descriptor
        matrix per detector, in object order."""
        keys = sorted(self.clouds)
        directions = sorted({d for _, d, _ in keys})
        detectors = sorted({f for c in self.clouds.values() for f in c.detectors})
        cols: dict[str, list] = {k: [] for k in ("key_point", "direction", "viewpoint", "detector", "region")}
        xyz, ends = [], []
        descriptors: dict[str, list[np.ndarray]] = {f: [] for f in detectors}
        for point, d, r in keys:
            cloud = self.clouds[(point, d, r)]
            n = len(cloud)
            cols["key_point"].append(np.full(n, point))
            cols["direction"].append(np.full(n, directions.index(d)))
            cols["viewpoint"].append(np.full(n, r))
            cols["detector"].append(np.array([detectors.index(f) for f in cloud.detectors], np.int64))
            cols["region"].append(cloud.region)
            xyz.append(cloud.xyz)
            ends.append(cloud.ends)
            for f, h in zip(cloud.detectors, cloud.descriptors, strict=True):
                descriptors[f].append(h)
        arrays = {k: np.concatenate(v).astype(np.int64) if v else np.zeros(0, int) for k, v in cols.items()}
        write_npz_atomic(
            path,
            **arrays,
            xyz=np.vstack(xyz).astype(np.float32) if xyz else np.zeros((0, 3), np.float32),
            ends=np.concatenate(ends).astype(np.float32) if ends else np.zeros((0, 2, 3), np.float32),
            **{f"H_{f}": np.stack(v) for f, v in descriptors.items()},
            meta=np.array(
                json.dumps(
                    {
                        "clouds": [[p, d, r] for p, d, r in keys],
                        "directions": directions,
                        "detectors": detectors,
                        "poses": [[p, r, *v.tolist()] for (p, r), v in sorted(self.poses.items())],
                        "origins": {str(p): v.tolist() for p, v in self.origins.items()},
                        "names": {str(p): n for p, n in self.names.items()},
                    }
                )
            ),
        )

    @classmethod
    def load(cls, path: str | Path) -> KeyObjectMap:
        try:
            data = np.load(path, allow_pickle=False)
            meta = json.loads(str(data["meta"]))
        except (OSError, KeyError, ValueError) as exc:
            raise OrthonavError(f"{path}: not a key object map (.npz of KeyObjectMap.save): {exc}") from exc
        model = cls(
            poses={(int(p), int(r)): np.array(v) for p, r, *v in meta["poses"]},
            origins={int(p): np.array(v) for p, v in meta["origins"].items()},
            names={int(p): n for p, n in meta["names"].items()},
        )
        rows = {f: iter(data[f"H_{f}"]) for f in meta["detectors"]}
        key = np.column_stack([data["key_point"], data["direction"], data["viewpoint"]])
        for point, d, r in meta["clouds"]:  # saved in this order, so descriptors follow it
            sel = np.flatnonzero((key == (point, meta["directions"].index(d), r)).all(axis=1))
            names = [meta["detectors"][i] for i in data["detector"][sel]]
            descriptors = [next(rows[f]) for f in names]
            xyz, region, ends = data["xyz"][sel], data["region"][sel], data["ends"][sel]
            model.add(int(point), d, int(r), KeyObjectCloud(xyz, names, descriptors, region, ends))
        return model
