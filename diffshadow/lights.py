"""Light directions: Fibonacci sphere, a region of it for training, held-out unseen directions.

A direction is a unit vector pointing toward the light (paper eq. 2). Spherical coordinates in the
JSON are (theta, phi): theta the polar angle from +z, phi the azimuth from +x toward +y, in radians.
"""

from __future__ import annotations

import heapq
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from diffshadow.io import atomic_write_text
from diffshadow.sampling import LightStream

if TYPE_CHECKING:  # light sets are read and written without torch (the lights and collect_weights jobs)
    import torch

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


class LightError(ValueError):
    """A light direction or light set that cannot be used."""


TINY_COMPONENT = 1e-9  # below this a unit direction's component is flushed to 0 (float32 would underflow it)


def as_direction(light_dir: ArrayLike, *, name: str = "light_dir") -> np.ndarray:
    """Validate and normalise one direction; rejects zero, non-finite and wrong-length input.

    Components below `TINY_COMPONENT` become exactly 0, so float32 and float64 code paths agree on
    which box faces a ray is parallel to (found by the stress suite: 1e-117 is 0 in float32 only).
    """
    try:
        w = np.asarray(light_dir, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise LightError(f"{name}: expected 3 numbers, got {light_dir!r}") from None
    if w.shape != (3,):
        raise LightError(f"{name}: expected 3 numbers (x, y, z), got {w.size}")
    if not np.all(np.isfinite(w)):
        raise LightError(f"{name}: must be finite, got {w.tolist()}")
    with np.errstate(over="ignore"):
        norm = float(np.linalg.norm(w))
    if norm < 1e-12:
        raise LightError(f"{name}: must be non-zero, got {w.tolist()}")
    if not np.isfinite(norm):  # components near float64's largest, whose squares overflow: scaled down first
        w = w / np.abs(w).max()
        norm = float(np.linalg.norm(w))
    w = w / norm
    w = np.where(np.abs(w) < TINY_COMPONENT, 0.0, w)
    return w / np.linalg.norm(w)


def fibonacci_sphere(n: int) -> np.ndarray:
    """`n` nearly uniform unit vectors on the sphere (golden spiral), deterministic. Returns (n, 3)."""
    if int(n) < 1:
        raise LightError(f"fibonacci_sphere: n must be >= 1, got {n}")
    i = np.arange(int(n), dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = GOLDEN_ANGLE * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def select_region(directions: ArrayLike, center: ArrayLike, count: int) -> np.ndarray:
    """Indices of the `count` directions closest in angle to `center` (ties by index)."""
    dirs = np.asarray(directions, dtype=np.float64)
    c = as_direction(center, name="center")
    if not 1 <= count <= len(dirs):
        raise LightError(f"select_region: count must be in 1..{len(dirs)}, got {count}")
    return np.argsort(-(dirs @ c), kind="stable")[:count]


LAYOUTS = ("rim", "cap")  # lights.layout; the first is the default
OLD_LAYOUT = "cap"  # what a light-set file without a `layout` key holds: made before lights.layout, or with cap


def layout_of(record: dict) -> str:
    """The `lights.layout` a light-set file (or a record copied from one, a sweep's point) was made with."""
    return record.get("layout", OLD_LAYOUT)


def rim_layout(directions: np.ndarray, center: ArrayLike) -> tuple[np.ndarray, int]:
    """`directions` (the training region of a Fibonacci sphere, `select_region`'s: nearest the centre first) with
    its outer shell moved onto the region's edge: the directions within one spacing of the edge (the cap around
    `center` that holds them all; the spacing √(cap area / count), √(4π / sphere points) for a Fibonacci region)
    are replaced by as many spread evenly on the edge's circle. The count and the cap stay, so unseen lights are
    drawn from the same cap; but the training lights' hull now reaches the cap's edge, where a Fibonacci region's
    hull left a rim of lights to extrapolate to (a fifth of the cap at 32 lights; docs/design.md, "The light
    layout"). Returns the directions (interior first, then the edge's by azimuth) and how many lie on the edge."""
    dirs = np.asarray(directions, dtype=np.float64)
    c = as_direction(center, name="center")
    angle = np.arccos(np.clip(dirs @ c, -1.0, 1.0))
    edge = float(angle.max())
    spacing = np.sqrt(4.0 * np.pi / len(dirs) * (1.0 - np.cos(edge)) / 2.0) if edge > 0 else 0.0
    k = int((angle > edge - spacing).sum())  # the last k: `directions` are nearest first
    if len(dirs) < 4 or k < 3:  # no hull to widen: a cap of 3 or fewer lights keeps them as they are
        return dirs, 0
    u, v = _orthonormal_basis(c)
    phi = 2.0 * np.pi * (np.arange(k) + 0.5) / k
    ring = np.sin(edge) * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v) + np.cos(edge) * c
    return np.concatenate([dirs[:len(dirs) - k], ring / np.linalg.norm(ring, axis=1, keepdims=True)]), k


def unseen_directions(train: ArrayLike, center: ArrayLike, count: int, *, seed: int | list[int] = 0,
                      min_angle: float = 1e-3) -> np.ndarray:
    """`count` random directions from the training set's cap around `center`, none equal to a training one.

    The cap is the smallest around `center` that holds every training direction; a candidate closer than
    `min_angle` radians to a training direction is drawn again. Returns (count, 3).
    """
    train = np.asarray(train, dtype=np.float64)
    c = as_direction(center, name="center")
    cos_max = float(np.min(train @ c))
    rng = np.random.default_rng(seed)
    basis = _orthonormal_basis(c)
    out: list[np.ndarray] = []
    for _ in range(1000):
        need = count - len(out)
        if need <= 0:
            break
        # uniform on the cap: cos(angle) uniform in [cos_max, 1]
        cos_t = rng.uniform(cos_max, 1.0, size=4 * need)
        phi = rng.uniform(0.0, 2.0 * np.pi, size=4 * need)
        sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None))
        cand = (sin_t * np.cos(phi))[:, None] * basis[0] + (sin_t * np.sin(phi))[:, None] * basis[1]
        cand += cos_t[:, None] * c
        closest = np.concatenate([np.max(block @ train.T, axis=1) for block in _blocks(cand, len(train))])
        keep = cand[closest < np.cos(min_angle)]
        out.extend(keep[:need])
    if len(out) < count:
        raise LightError(f"unseen_directions: could not find {count} directions apart from the training set")
    return np.asarray(out[:count]).reshape(-1, 3)


def pick(n_total: int, n: int) -> list[int]:
    """`n` indices spread evenly over 0..n_total-1 (the first and last included)."""
    if n <= 0 or n_total == 0:
        return []
    return sorted(set(np.linspace(0, n_total - 1, min(n, n_total)).round().astype(int).tolist()))


def nearest(train: np.ndarray, query: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (Q, k) of the k training directions closest in angle, and their angles (Q, k); all of them, nearest
    first, where there are fewer than k (a run of 3 training lights blends its pool lights' targets from 3)."""
    k = min(k, len(train))
    # elementwise products summed x, y, z in order, not `@`: a BLAS product sums in an order the library picks
    # at run time (threads, code path), and a last-bit difference in an angle moved the blend baseline's PSNR
    # between two runs. (The same sums as `(q[:, None] * train[None]).sum(-1)`, without its (Q, N, 3) array.)
    idx, angles = [], []
    for q in _blocks(query, len(train)):  # rows are independent: blocks give the same bytes in bounded memory
        cos = np.clip(q[:, 0:1] * train[:, 0] + q[:, 1:2] * train[:, 1] + q[:, 2:3] * train[:, 2], -1, 1)
        i = _top_k_stable(cos, k)
        idx.append(i)
        angles.append(np.arccos(np.take_along_axis(cos, i, axis=1)))
    return np.concatenate(idx), np.concatenate(angles)


def _top_k_stable(cos: np.ndarray, k: int) -> np.ndarray:
    """Columns of the k largest values of each row, largest first, ties by column: the first k of a stable
    argsort of -cos, without sorting whole rows (a partition finds each row's k-th value; only the few columns
    at or above it are sorted)."""
    if len(cos) == 0 or k == 0:
        return np.zeros((len(cos), k), dtype=np.int64)
    kth = np.take_along_axis(cos, np.argpartition(-cos, k - 1, axis=1)[:, k - 1:k], axis=1)
    rows, cols = np.nonzero(cos >= kth)  # k per row, more where the k-th value is tied
    order = np.lexsort((cols, -cos[rows, cols], rows))  # by row, then value (largest first), then column
    rows, cols = rows[order], cols[order]
    start = np.searchsorted(rows, np.arange(len(cos)))
    return cols[start[:, None] + np.arange(k)]


BLOCK_PAIRS = 1 << 22  # (query, training light) pairs per block: ~100 MB of float64 products


def _blocks(rows: np.ndarray, n_train: int) -> list[np.ndarray]:
    """`rows` in blocks of at most BLOCK_PAIRS / n_train (at least one block, maybe empty): the pool at 2000
    lights x 64 (128k directions against 2000 lights) would otherwise take 6 GB at once."""
    step = max(1, BLOCK_PAIRS // max(1, n_train))
    return [rows[i:i + step] for i in range(0, max(1, len(rows)), step)]


def inverse_angle_weights(angles: np.ndarray) -> np.ndarray:
    """Blend weights (Q, k) summing to 1 from `nearest`'s angles (Q, k)."""
    w = 1.0 / np.maximum(angles, 1e-6)
    return w / w.sum(axis=1, keepdims=True)


WEIGHTINGS = ("triangle", "inverse-angle")  # evaluate.blend_weights: how a light's stored SIRENs are blended
OLD_WEIGHTING = "inverse-angle"  # what a store or metrics file made before evaluate.blend_weights used


def recorded_weighting(record: dict) -> str:
    """The weighting a store's or a metrics file's blend record names; a record made before the key existed was
    blended by OLD_WEIGHTING."""
    return record.get("blend_weights", OLD_WEIGHTING)


def check_weighting(weighting: str, key: str = "evaluate.blend_weights") -> str:
    """`weighting` if it names a blend (WEIGHTINGS), else a LightError naming the config `key`."""
    if weighting not in WEIGHTINGS:
        raise LightError(f"{key}: expected one of {', '.join(WEIGHTINGS)}, got {weighting!r}")
    return weighting


def blend_weights(train: np.ndarray, query: np.ndarray, k: int, weighting: str) -> tuple[np.ndarray, np.ndarray]:
    """The training directions a weight blend of each query takes (Q, m) and their weights (Q, m) summing to 1.
    `weighting` "triangle": the three corners of the training lights' spherical Delaunay triangle around the
    query, barycentric weights (`Triangulation`; `k` unused); "inverse-angle": the k nearest."""
    return blend_finder(train, k, weighting)(query)


def blend_finder(train: np.ndarray, k: int,
                 weighting: str) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """`blend_weights` for these training lights as a function of the queries, its triangulation made once (a
    viewer or a timing loop asks for one light at a time)."""
    if weighting == "triangle":
        return Triangulation(train).weights
    check_weighting(weighting)

    def find(query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx, angles = nearest(train, query, k)
        return idx, inverse_angle_weights(angles)

    return find


def blend_label(record: dict) -> str:
    """"triangle blend of the" or "blend of k nearest", for a metrics record's `blend_weights` and `blend_k` (a
    record made before the key: inverse-angle)."""
    if recorded_weighting(record) == "triangle":
        return "triangle blend of the"
    return f"blend of {record['blend_k']} nearest"


def describe_blend(weighting: str, k: int) -> str:
    """The weight blend in words, for logs and the report."""
    if weighting == "triangle":
        return "the weight blend of the stored SIRENs at the corners of its triangle"
    return f"the weight blend of the {k} nearest stored SIRENs"


class Triangulation:
    """The training lights' spherical Delaunay triangulation, and barycentric blend weights over it.

    A light inside a triangle gets its three corners, weighted by its barycentric coordinates in the flat
    triangle (the direction is their weighted sum up to length): the weights reproduce the light's direction
    exactly, move continuously across edges, and give a training light its own SIREN alone. The k nearest with
    inverse-angle weights do neither, and jump where the k-th nearest light changes (docs/performance.md, "The
    weight blend: the triangle around the light").

    The triangles are the faces of the lights' convex hull (every light lies on the sphere, so each face's
    circumscribed cap holds no other light). Where the lights do not surround the origin (a cap of the sphere),
    the hull is taken with one more point, the antipode of their mean direction: its faces fan from the region's
    rim to that point, so every direction lies in exactly one face. A light past the rim, in a fan face, gets the
    rim edge's two lights, weighted by where it lies along that edge; the rim's slivers are opened first
    (`_open_rim_slivers`), so a light lying just inside a rim edge is a rim light itself."""

    def __init__(self, train: np.ndarray):
        train = np.asarray(train, dtype=np.float64).reshape(-1, 3)
        self.n = len(train)
        points, self.faces = train, None
        total = train.sum(axis=0)
        hole = -total / np.linalg.norm(total) if np.linalg.norm(total) > 1e-9 * max(1, self.n) else None
        for extra in ((None, hole) if hole is not None else (None,)):
            points = train if extra is None else np.vstack([train, extra])
            faces = _hull_faces(points)
            if faces is not None and (extra is not None or _surrounds_origin(points, faces)):
                self.faces = faces
                break
        self.points = points
        if self.faces is None:  # fewer than 3 lights, or all on one great circle: no triangles
            return
        if len(points) > self.n:
            self.faces = _open_rim_slivers(points, self.faces, self.n)
        a, b, c = (points[self.faces[:, i]] for i in range(3))
        # q = la a + lb b + lc c by Cramer's rule: la = det(q, b, c) / det(a, b, c), and so on
        self.cross = np.stack([np.cross(b, c), np.cross(c, a), np.cross(a, b)], axis=1)  # (F, 3 corners, 3)
        self.det = _dot3(a, self.cross[:, 0])
        # each face's circumscribed cap {x: n . x >= cos}, cut by the face's plane: it holds the face's part of the
        # sphere where the origin lies inside the hull (cos > 0), and no other light (the faces are Delaunay)
        normal = np.cross(b - a, c - a)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        cos = _dot3(normal, a)
        self.cap_normal, self.cap_cos = np.where(cos[:, None] < 0, -normal, normal), np.abs(cos)
        self._index_caps()

    def _index_caps(self) -> None:
        """A k-d tree over the centres of the faces' caps of about the lights' spacing, searched as far as the
        widest of them reaches; the wide ones (the fan past a region's rim, ~60 degrees) are tested directly,
        and a face whose plane does not leave the origin inside (no cap) everywhere."""
        from scipy.spatial import cKDTree

        capped = self.cap_cos > CAP_SLACK
        radius = np.arccos(np.clip(self.cap_cos, -1.0, 1.0))
        small = capped & (radius <= WIDE_CAP * np.median(radius[capped])) if capped.any() else capped
        self._small, self._wide, self._everywhere = (np.flatnonzero(m) for m in (small, capped & ~small, ~capped))
        self._tree = cKDTree(self.cap_normal[self._small])
        # |x - n|^2 = 2 - 2 n . x for unit x and n: the chord to the rim of the widest small cap
        self._reach = float(np.sqrt(2.0 - 2.0 * (self.cap_cos[self._small].min() - CAP_SLACK))) if small.any() else 0.0

    def weights(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Corners (Q, 3) and barycentric weights (Q, 3) summing to 1 (the nearest lights with inverse-angle
        weights where there are no triangles: fewer than three lights, or lights on one great circle)."""
        query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
        norm = np.linalg.norm(query, axis=1)
        if not np.all(np.isfinite(norm) & (norm > 0)):
            bad = int(np.flatnonzero(~(np.isfinite(norm) & (norm > 0)))[0])
            raise LightError(f"blend query {bad}: expected a finite nonzero direction, got {query[bad].tolist()}")
        if self.faces is None:
            idx, angles = nearest(self.points[:self.n], query, min(3, self.n))
            return idx, inverse_angle_weights(angles)
        if not len(query):  # `lights.unseen: 0`
            return np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3))
        face, lam = self.holding(query)
        idx = self.faces[face]
        lam = np.clip(lam, 0.0, None)
        real = idx < self.n
        lam = np.where(real, lam, 0.0)  # the antipode's share: a light past the rim takes the rim edge's lights
        idx = np.where(real, idx, np.take_along_axis(idx, np.argmax(real, axis=1)[:, None], axis=1))
        total = lam.sum(axis=1, keepdims=True)
        lam = np.where(total > 0, lam / np.where(total > 0, total, 1.0), real / real.sum(axis=1, keepdims=True))
        return idx, lam

    def holding(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The face (Q,) that holds each query (Q, 3) (nonzero directions) and the query's barycentric coordinates
        in it (Q, 3). The faces' cones tile the sphere, so every other face has a negative coordinate; on a shared
        edge both give the same weights, and ties go to the first (faces are sorted)."""
        pair_query, pair_face = self._candidates(query / np.linalg.norm(query, axis=1, keepdims=True))
        coords = _dot3(query[pair_query, None, :], self.cross[pair_face]) / self.det[pair_face, None]  # (P, 3)
        order = np.lexsort((pair_face, -coords.min(axis=1), pair_query))
        first = order[np.r_[True, pair_query[order][1:] != pair_query[order][:-1]]]
        return pair_face[first], coords[first]

    def _candidates(self, unit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(query, face) pairs sorted by query, among them each query's face and every face that could tie with
        it: the faces whose circumscribed cap holds the query, widened by CAP_SLACK (a face that does not hold a
        direction lies outside its cap by far more than rounding), and the faces without a cap. Testing every
        face instead cost 25 s for the 128,000 pool lights of 2,000 training lights (docs/performance.md, "The
        weight blend: the triangle around the light")."""
        near = self._tree.query_ball_point(unit, self._reach) if len(self._small) else [[]] * len(unit)
        counts = np.fromiter(map(len, near), dtype=np.int64, count=len(unit))
        near_query = np.repeat(np.arange(len(unit)), counts)
        near_face = self._small[np.concatenate([np.asarray(n, dtype=np.int64) for n in near] + [np.zeros(0, np.int64)])]
        held = _dot3(unit[near_query], self.cap_normal[near_face]) >= self.cap_cos[near_face] - CAP_SLACK
        wide_query, wide = np.nonzero(unit @ self.cap_normal[self._wide].T >= self.cap_cos[self._wide] - CAP_SLACK)
        every_query = np.repeat(np.arange(len(unit)), len(self._everywhere))
        pair_query = np.concatenate([near_query[held], wide_query, every_query])
        pair_face = np.concatenate([near_face[held], self._wide[wide], np.tile(self._everywhere, len(unit))])
        if len(np.unique(pair_query)) < len(unit):
            raise AssertionError("a blend query outside every face's cap: the triangulation does not cover it")
        order = np.lexsort((pair_face, pair_query))
        return pair_query[order], pair_face[order]


CAP_SLACK = 1e-7  # a face's circumscribed cap widened by this much cosine: rounding is ~1e-16
WIDE_CAP = 4.0  # a face's cap wider than this many times the median is tested directly, not through the tree


RIM_SLIVER_DEG = 135.0  # a rim triangle whose angle opposite the rim is wider is a sliver: its corner joins the rim


def _open_rim_slivers(points: np.ndarray, faces: np.ndarray, hole: int) -> np.ndarray:
    """`faces` with the rim's slivers opened: a triangle (a, b, c) on the rim edge ab whose angle at c exceeds
    RIM_SLIVER_DEG, with the fan face (a, b, hole), becomes the fan faces (a, c, hole) and (c, b, hole), so c,
    which lies almost on the rim, becomes a rim light (an edge flip: the same quadrilateral, still tiled).

    The convex hull's rim skips lights that lie just inside it (a cap's outermost lights are nearly on a circle):
    at 32 lights 8 rim edges, 5 of them over such a light at 160-170 degrees, so a light just past the rim next
    to one got the rim edge's two lights, each a spacing or more away, and none of the one beside it. Triangles
    are opened widest first (ties by their corners' coordinates), the same whatever order the lights come in;
    a new rim edge is examined in its turn (docs/performance.md, "Past the rim: the slivers opened")."""
    cos_max = np.cos(np.radians(RIM_SLIVER_DEG))
    start = faces.tolist()
    faces, alive = [], []
    by_edge: dict[tuple[int, int], list[int]] = {}
    heap: list = []  # (cos of the angle opposite the rim edge, its corners' coordinates, fan face, inner face, c)

    def add(face) -> int:
        faces.append(tuple(sorted(face)))  # the hole, index n, sorts last
        alive.append(True)
        a, b, c = faces[-1]
        for edge in ((a, b), (a, c), (b, c)):
            by_edge.setdefault(edge, []).append(len(faces) - 1)
        return len(faces) - 1

    def examine(fan: int) -> None:
        a, b = faces[fan][:2]
        inner = [i for i in by_edge[(a, b)] if alive[i] and hole not in faces[i]]
        if len(inner) != 1:
            return
        c = next(v for v in faces[inner[0]] if v not in (a, b))
        u, w = points[a] - points[c], points[b] - points[c]
        cos = _dot3(u, w) / (np.sqrt(_dot3(u, u)) * np.sqrt(_dot3(w, w)))
        if cos < cos_max:  # widest first; ties by the corners' coordinates, not their indices
            heapq.heappush(heap, (float(cos), sorted((tuple(points[a]), tuple(points[b]))), fan, inner[0], c))

    for face in start:
        add(face)
    rim = {v for f in faces if f[2] == hole for v in f[:2]}
    for fan in [i for i, f in enumerate(faces) if f[2] == hole]:
        examine(fan)
    while heap:
        *_, fan, inner, c = heapq.heappop(heap)
        if not (alive[fan] and alive[inner]) or c in rim:  # the edge was opened already, or c joined the rim
            continue
        a, b = faces[fan][:2]
        normal = np.cross(points[c], points[hole])  # a and b on either side of the plane (c, hole): still tiled
        if np.sign(_dot3(normal, points[a])) * np.sign(_dot3(normal, points[b])) >= 0:
            continue
        alive[fan] = alive[inner] = False
        rim.add(c)
        examine(add((a, c, hole)))
        examine(add((c, b, hole)))
    out = np.array([f for f, keep in zip(faces, alive, strict=True) if keep], dtype=np.int64)
    return out[np.lexsort(out.T[::-1])]


def _dot3(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x . y over the last axis, summed x, y, z in order (see `nearest`: the same bytes whatever BLAS does)."""
    return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2]


def _hull_faces(points: np.ndarray) -> np.ndarray | None:
    """The convex hull's triangles (F, 3) as sorted corner indices, in sorted order (the same faces whatever
    order Qhull lists them in); None where there is no hull (fewer than 4 points, or all in one plane)."""
    from scipy.spatial import ConvexHull, QhullError

    if len(points) < 4:
        return None
    try:
        faces = np.sort(ConvexHull(points).simplices, axis=1)
    except QhullError:
        return None
    return faces[np.lexsort(faces.T[::-1])]


def _surrounds_origin(points: np.ndarray, faces: np.ndarray) -> bool:
    """Whether the origin lies inside the hull: every face's plane has it on the inner side."""
    a, b, c = (points[faces[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    centroid = points.mean(axis=0)
    # orient each normal away from the hull's centroid; the origin is inside when it is behind every face
    sign = np.sign(_dot3(normal, a - centroid))
    return bool(np.all(sign * _dot3(normal, -a) < 0))


INSIDE_TOLERANCE_DEG = 1e-6  # a training light on the cap's edge is inside it despite rounding


@dataclass(frozen=True)
class LightRegion:
    """The light directions a shadow cache was trained for: the cap around `center` that holds every training
    light (`radius_deg`, the cap `unseen_directions` and the pool lights are drawn in), the training lights'
    spacing (median angle to the nearest other one) and `far_deg`, the farthest any unseen test light sat from
    its nearest training light: the evaluation vouches for lights up to that far, no farther. It travels with
    the weight stores (attrs `region`) and the diffusion checkpoints (key `region`)."""

    center: tuple[float, float, float]
    radius_deg: float
    spacing_deg: float
    far_deg: float
    train: np.ndarray  # (N, 3) the training lights, to measure a light's distance to the nearest

    @classmethod
    def of(cls, train: np.ndarray, unseen: np.ndarray | None = None, center: ArrayLike | None = None) -> LightRegion:
        """The region of training lights `train` (N, 3) (centre: `center`, else their mean direction)."""
        train = np.asarray(train, dtype=np.float64).reshape(-1, 3)
        if not len(train):
            raise LightError("a light region needs at least one training light")
        c = as_direction(center if center is not None else train.mean(axis=0), name="region center")
        radius = float(np.degrees(np.arccos(np.clip(np.min(train @ c), -1.0, 1.0))))
        spacing = float(np.degrees(np.median(nearest(train, train, 2)[1][:, 1]))) if len(train) > 1 else 0.0
        far = spacing
        if unseen is not None and len(unseen):
            far = float(np.degrees(np.max(nearest(train, np.asarray(unseen, dtype=np.float64), 1)[1])))
        return cls(tuple(float(x) for x in c), radius, spacing, far, train)

    @classmethod
    def recorded(cls, d: dict | None, train: np.ndarray) -> LightRegion:
        """The region recorded with a cache (`to_dict`), else (a cache from before regions travelled with it) the
        cap around its training lights' mean direction."""
        return cls.from_dict(d, train) if d else cls.of(train)

    @classmethod
    def from_dict(cls, d: dict, train: np.ndarray) -> LightRegion:
        return cls(tuple(float(x) for x in d["center"]), float(d["radius_deg"]), float(d["spacing_deg"]),
                   float(d["far_deg"]), np.asarray(train, dtype=np.float64).reshape(-1, 3))

    def to_dict(self) -> dict:
        return {"center": list(self.center), "radius_deg": self.radius_deg, "spacing_deg": self.spacing_deg,
                "far_deg": self.far_deg}

    def angle_to_center(self, light: ArrayLike) -> float:
        """Degrees between `light` and the cap's centre."""
        cos = float(as_direction(light) @ np.asarray(self.center))
        return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))

    def holds(self, angle_to_center_deg: float) -> bool:
        """Whether a light this far from the centre lies in the cap (a training light on its edge does)."""
        return angle_to_center_deg <= self.radius_deg + INSIDE_TOLERANCE_DEG

    def contains(self, light: ArrayLike) -> bool:
        """Whether `light` lies in the cap (its angle to the centre only: no search of the training lights)."""
        return self.holds(self.angle_to_center(light))

    def where(self, light: ArrayLike) -> RegionCheck:
        """Where `light` stands: its angle to the centre and to the nearest training light, inside or not."""
        w = as_direction(light)
        return RegionCheck(self, self.angle_to_center(w), float(np.degrees(nearest(self.train, w[None], 1)[1][0, 0])))

    def describe(self) -> str:
        c = ", ".join(f"{x:.3g}" for x in self.center)
        return (f"a {self.radius_deg:.1f}° cap around ({c}) of {len(self.train)} training lights "
                f"{self.spacing_deg:.1f}° apart")


@dataclass(frozen=True)
class RegionCheck:
    region: LightRegion
    to_center_deg: float
    to_nearest_deg: float

    @property
    def inside(self) -> bool:
        return self.region.holds(self.to_center_deg)

    @property
    def far(self) -> bool:
        """Inside, but farther from every training light than any unseen test light was (not evaluated there)."""
        return self.inside and self.to_nearest_deg > self.region.far_deg + INSIDE_TOLERANCE_DEG

    def message(self) -> str:
        """One line on a light outside the region or far inside it: what a cached answer for it is worth."""
        r = self.region
        if not self.inside:
            return (f"the light is outside the cache's region ({r.describe()}): {self.to_center_deg:.1f}° from its "
                    f"centre, {self.to_center_deg - r.radius_deg:.1f}° past its edge, {self.to_nearest_deg:.1f}° from "
                    f"the nearest training light; the cache holds nothing there")
        return (f"the light is inside the cache's region but {self.to_nearest_deg:.1f}° from the nearest training "
                f"light, farther than any unseen test light was ({r.far_deg:.1f}°): the cache was not evaluated "
                f"that far out")


def training_pool(train: ArrayLike, center: ArrayLike, n: int, *, seed: int) -> np.ndarray:
    """`n` random directions in the training lights' cap for diffusion training on exact shadows only (no
    fitted SIREN): drawn like the unseen test set but from another random stream, so never the same lights."""
    return unseen_directions(train, center, n, seed=[seed, LightStream.POOL])


def validation_lights(train: ArrayLike, center: ArrayLike, n: int, *, seed: int) -> np.ndarray:
    """`n` random directions in the training lights' cap for choosing the fine-tuned model: drawn like the
    unseen test set, so they stand for it, but from a third random stream (never a test or pool light).
    Halfway points between neighbouring training lights had stood in before; they disagreed with the test
    set on whether fine-tuning helped (nucleon: +0.8 dB there, -0.4 dB on the unseen lights)."""
    return unseen_directions(train, center, n, seed=[seed, LightStream.VALIDATION])


def wide_test_lights(train: ArrayLike, center: ArrayLike, n: int, *, seed: int) -> np.ndarray:
    """`n` further test lights for evaluate_voxels' wide comparison: drawn like the unseen test set, from a fourth
    random stream (never a test, pool or validation light, so never one the mix's share was chosen on)."""
    return unseen_directions(train, center, n, seed=[seed, LightStream.WIDE])


def _orthonormal_basis(c: np.ndarray) -> np.ndarray:
    helper = np.array([1.0, 0.0, 0.0]) if abs(c[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(c, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(c, u)])


def to_spherical(directions: ArrayLike) -> np.ndarray:
    """(n, 3) unit vectors → (n, 2) of (theta, phi) in radians."""
    d = np.asarray(directions, dtype=np.float64)
    theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    phi = np.arctan2(d[:, 1], d[:, 0])
    return np.stack([theta, phi], axis=1)


def make_light_sets(sphere: int, count: int, center: ArrayLike, unseen: int, seed: int = 0,
                    layout: str = "rim") -> dict:
    """Training directions (a region of a Fibonacci sphere; with `layout` "rim" its outer shell moved onto the
    region's edge, `rim_layout`) and held-out unseen ones, as a JSON-able dict."""
    # the workflow's schema holds these; the `lights` command and the library get them here, by name
    for name, value, least in (("sphere", sphere, 1), ("count", count, 1), ("unseen", unseen, 0), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise LightError(f"{name}: expected an integer >= {least}, got {value!r}")
    if layout not in LAYOUTS:
        raise LightError(f"layout: expected one of {', '.join(LAYOUTS)}, got {layout!r}")
    sphere_dirs = fibonacci_sphere(sphere)
    idx = select_region(sphere_dirs, center, count)
    train, on_edge = sphere_dirs[idx], 0
    if layout == "rim":
        train, on_edge = rim_layout(train, center)
        idx = np.concatenate([idx[:count - on_edge], np.full(on_edge, -1)])  # the edge's lights are no sphere point
    held = unseen_directions(train, center, unseen, seed=seed) if unseen > 0 else np.zeros((0, 3))
    return {
        "sphere": int(sphere),
        "center": as_direction(center, name="center").tolist(),
        "seed": int(seed),
        **({"layout": layout, "on_edge": on_edge} if layout != OLD_LAYOUT else {}),  # cap: the same bytes as before
        "spherical_convention": "theta: polar angle from +z; phi: azimuth from +x toward +y; radians",
        "train": {
            "sphere_index": idx.tolist(),
            "cartesian": train.tolist(),
            "spherical": to_spherical(train).tolist(),
        },
        "unseen": {"cartesian": held.tolist(), "spherical": to_spherical(held).tolist()},
    }


def configured_light_sets(lights: dict) -> dict:
    """`make_light_sets` for a config's `lights` section (sphere, count, center, unseen, seed, layout): the sets the
    workflow's `lights` job writes, for code that needs them before that file exists."""
    return make_light_sets(int(lights["sphere"]), int(lights["count"]), lights["center"], int(lights["unseen"]),
                           seed=int(lights["seed"]), layout=lights["layout"])


def write_lights(path: str | Path, lights: dict) -> None:
    """Write a light-set dict as JSON, atomically."""
    atomic_write_text(path, json.dumps(lights, indent=1) + "\n")


def read_lights(path: str | Path) -> dict:
    """Read a light-set JSON; `train`/`unseen` come back as (n, 3) float64 arrays."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
        train = np.asarray(d["train"]["cartesian"], dtype=np.float64)
        unseen = np.asarray(d["unseen"]["cartesian"], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise LightError(f"{path}: not a light-set file ({e})") from None
    # the `lights` job writes unit directions, one row each; a file edited by hand is named here, not as an
    # unnamed lights[i] deep in a stage or, flat or of another length, read as other lights
    train, unseen = (a.reshape(0, 3) if a.size == 0 else a for a in (train, unseen))
    for key, dirs in (("train", train), ("unseen", unseen)):
        if dirs.ndim != 2 or dirs.shape[1] != 3:
            raise LightError(f"{path}: {key}.cartesian has shape {dirs.shape}, expected one [x, y, z] a light")
        off = ~(np.abs(np.linalg.norm(dirs, axis=1) - 1) < 1e-6)  # NaN too
        if off.any():
            i = int(np.flatnonzero(off)[0])
            raise LightError(f"{path}: {key}.cartesian[{i}] = {dirs[i].tolist()} is not a unit direction; "
                             "rerun the lights job that writes it")
    if len(train) == 0:
        raise LightError(f"{path}: no training lights")
    return {**d, "train": train, "unseen": unseen}


def n_subsets(n_lights: int, subset_size: int) -> int:
    """Light subsets of a scene: S = ceil(n / size), numbered 0..S-1."""
    return -(-n_lights // subset_size)


def light_subsets(train: ArrayLike, subset_size: int) -> list[list[int]]:
    """The training lights split into S = ceil(n / size) compact patches of the sphere, each `subset_size`
    lights (the last one fewer), as sorted light indices; subset s is the s-th list.

    Recursive bisection: a set of g subsets' worth of lights is cut across its widest coordinate into the
    first floor(g / 2) subsets' lights and the rest. Compact patches keep a pool light's nearest training
    lights in its own subset, which is what the blend loss couples: runs of consecutive indices are rings
    around the centre (the lights are ordered by angle from it), and at the paper's 2000 lights in subsets of
    50 only 2 % of pool lights had all 4 nearest in their subset, against 65 % here (docs/performance.md).
    One subset is every light in order, so a run with count <= subset_size is unchanged. Deterministic: it
    compares coordinates only (stable sorts), no sums in a library-chosen order."""
    dirs = np.asarray(train, dtype=np.float64).reshape(-1, 3)
    size = _check_size(subset_size)
    if len(dirs) == 0:
        raise LightError("light_subsets: no training lights")

    def split(idx: np.ndarray) -> list[list[int]]:
        if len(idx) <= size:
            return [sorted(idx.tolist())]
        first = (n_subsets(len(idx), size) // 2) * size
        pts = dirs[idx]
        axis = int(np.argmax(pts.max(axis=0) - pts.min(axis=0)))
        order = idx[np.argsort(pts[:, axis], kind="stable")]
        return split(order[:first]) + split(order[first:])

    return split(np.arange(len(dirs)))


def across_subsets(train: ArrayLike, idx: np.ndarray, mix: np.ndarray, subset_size: int) -> np.ndarray:
    """(Q,) bool: whether each query's blend (`blend_weights`' `idx`, `mix`) takes lights with weight from more
    than one of `light_subsets(train, subset_size)`: a seam, where the blend loss of separate fit_siren jobs
    coupled its SIRENs only through a halo (`fit.halo`), or not at all."""
    label = np.empty(len(np.asarray(train).reshape(-1, 3)), dtype=np.int64)
    for s, lights in enumerate(light_subsets(train, subset_size)):
        label[lights] = s
    sub = np.where(np.asarray(mix) > 1e-6, label[np.asarray(idx)], -1)
    first = sub[np.arange(len(sub)), np.argmax(sub >= 0, axis=1)]
    return ((sub != first[:, None]) & (sub >= 0)).any(axis=1)


def subset_indices(train: ArrayLike, subset_size: int, subset: int) -> list[int]:
    """Lights of subset `subset` (0..S-1, S = ceil(n / size)): its patch of `light_subsets`."""
    check_subset(len(np.asarray(train).reshape(-1, 3)), subset_size, subset)
    return light_subsets(train, subset_size)[subset]


def check_subset(n_lights: int, subset_size: int, subset: int) -> None:
    """ValueError unless `n_lights` in subsets of `subset_size` have a subset `subset` (the fit's check, and the
    workflow's before it plans a job for one)."""
    count = n_subsets(n_lights, _check_size(subset_size))
    if not 0 <= subset < count:
        raise ValueError(f"subset {subset} does not exist: {n_lights} lights in subsets of {subset_size} "
                         f"give subsets 0..{count - 1}")


def _check_size(subset_size: int) -> int:
    if int(subset_size) < 1:
        raise ValueError(f"subset_size must be >= 1, got {subset_size}")
    return int(subset_size)


def index_ranges(idx: list[int]) -> str:
    """Sorted light indices as runs, e.g. [0, 1, 2, 5, 7, 8] -> "0-2, 5, 7-8" (for log lines)."""
    runs: list[list[int]] = []
    for i in idx:
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)


BLEND_K = 4  # training SIRENs blended into a pool light's x0 target (the evaluation's blend baseline: 4 too)
# the diffusion model's pool lights' x0 targets: the triangle blend's lost (the model alone -0.69 / -0.50 dB, the mix
# -0.32 / -0.29 on validation lights, seeds 0 / 1) and, over SIRENs fitted toward it, tied (-0.01, the mix -0.06;
# e1cc08b; docs/performance.md, "Whole runs with it"), while stage 1's blend loss gains by it
POOL_X0_WEIGHTING = "inverse-angle"


@dataclass
class PoolLights:
    """Pool lights: directions in the training lights' cap with no fitted SIREN. Each has an x0 target, a weight
    blend of training SIRENs (`neighbours`, `blend`: stage 1's blend loss by `fit.blend_weights`, the diffusion
    model's by POOL_X0_WEIGHTING), and its exact shadow at presampled points for the geometry loss. The blend
    alone is a usable SIREN because every training SIREN starts from one pre-optimised init (nucleon: 30.0 dB at
    unseen lights against 27.9 for blending the shadows themselves); the geometry loss corrects it towards the
    truth."""

    lights: torch.Tensor  # (M, 3)
    points: torch.Tensor  # (M, P, 3)
    values: torch.Tensor  # (M, P)
    neighbours: torch.Tensor  # (M, k) rows of the training set
    blend: torch.Tensor  # (M, k), rows sum to 1

    def to(self, device: torch.device | str) -> PoolLights:
        return PoolLights(*(t.to(device) for t in (self.lights, self.points, self.values, self.neighbours,
                                                    self.blend)))

    def x0(self, z_all: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
        """The x0 targets (B, n_params) of pool lights `j`: their blends of the standardised training weights."""
        # index_select, not z_all[index]: its backward (the fit's blend loss) adds the rows in index order at any
        # thread count, where indexing's accumulating index_put differs between runs on two threads
        rows = self.neighbours[j]
        return (z_all.index_select(0, rows.reshape(-1)).view(*rows.shape, -1) * self.blend[j][..., None]).sum(1)

    def samples(self, j: torch.Tensor, pick: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points (B, G, 3) and exact shadow (B, G) of pool lights `j` at their presampled points `pick` (B, G)."""
        return self.points[j].gather(1, pick[..., None].expand(-1, -1, 3)), self.values[j].gather(1, pick)
