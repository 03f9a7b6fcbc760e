import json
import warnings

import numpy as np
import pytest

from diffshadow.cli import main
from diffshadow.lights import (
    LightError,
    fibonacci_sphere,
    make_light_sets,
    read_lights,
    select_region,
    unseen_directions,
)


def test_fibonacci_sphere_is_unit_deterministic_and_even():
    d = fibonacci_sphere(1000)
    assert d.shape == (1000, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(d, fibonacci_sphere(1000))
    assert np.abs(d.mean(axis=0)).max() < 2e-3  # no hemisphere favoured
    # nearly uniform: every point's nearest neighbour is at a similar distance
    nn = np.sort(np.arccos(np.clip(d @ d.T, -1, 1)), axis=1)[:, 1]
    assert nn.max() / nn.min() < 2.0


def test_select_region_takes_the_closest():
    d = fibonacci_sphere(500)
    center = np.array([1.0, 1.0, 0.0])
    idx = select_region(d, center, 50)
    cos = d @ (center / np.linalg.norm(center))
    assert len(set(idx.tolist())) == 50
    assert cos[idx].min() >= np.delete(cos, idx).max()


CAP_CENTER = (0.0, 0.3, 1.0)


def cap_lights(n: int) -> np.ndarray:
    """`n` Fibonacci directions around CAP_CENTER: a training set."""
    d = fibonacci_sphere(800)
    return d[select_region(d, CAP_CENTER, n)]


def assert_in_cap_apart(dirs: np.ndarray, train: np.ndarray) -> None:
    """Inside the training lights' cap around CAP_CENTER, and none of them a training light."""
    c = np.asarray(CAP_CENTER) / np.linalg.norm(CAP_CENTER)
    assert (dirs @ c).min() >= (train @ c).min() - 1e-12
    assert (dirs @ train.T).max() < np.cos(1e-3)


def test_unseen_in_region_and_disjoint():
    train = cap_lights(200)
    unseen = unseen_directions(train, CAP_CENTER, 50, seed=3)
    assert_in_cap_apart(unseen, train)
    np.testing.assert_array_equal(unseen, unseen_directions(train, CAP_CENTER, 50, seed=3))


def test_a_direction_is_its_normalised_self_at_any_finite_scale():
    """Components near float64's largest (whose squares overflow the norm) give the direction of (1, 1, 1) or
    (1, 0, 0), without a warning; the usual scale is untouched (the same bytes as plain division by the norm)."""
    from diffshadow.lights import as_direction

    ones = np.ones(3) / np.linalg.norm(np.ones(3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for scale in (1e308, 1.7e308, 1e150, 1.0, 1e-3):
            np.testing.assert_allclose(as_direction([scale] * 3), ones, rtol=1e-15)
    assert np.array_equal(as_direction([1e308, 0, 0]), [1.0, 0.0, 0.0])
    assert np.array_equal(as_direction([0.3, -0.5, 0.8]), np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]))


def test_bad_center_and_count():
    d = fibonacci_sphere(10)
    with pytest.raises(LightError, match="center: must be non-zero"):
        select_region(d, (0, 0, 0), 3)
    with pytest.raises(LightError, match="center: must be finite"):
        select_region(d, (np.nan, 0, 1), 3)
    with pytest.raises(LightError, match=r"count must be in 1..10"):
        select_region(d, (0, 0, 1), 11)


@pytest.mark.parametrize("key, value, least", [("unseen", -2, 0), ("seed", -1, 0), ("sphere", 0, 1), ("count", 0, 1),
                                               ("unseen", 2.5, 0)])
def test_light_set_sizes_and_seed_are_named_when_bad(key, value, least):
    """A negative unseen count wrote '-2 unseen directions' (no set at all); a negative seed got numpy's nameless
    'expected non-negative integer'."""
    args = {"sphere": 100, "count": 4, "center": (0, 0, 1), "unseen": 2, "seed": 0, key: value}
    with pytest.raises(LightError, match=rf"^{key}: expected an integer >= {least}, got {value!r}$"):
        make_light_sets(**args)


@pytest.mark.parametrize("key, rows, said", [
    ("train", [[0.0, 0.0, 1.0, 1.0, 0.0, 0.0]],
     r"train.cartesian has shape \(1, 6\), expected one \[x, y, z\] a light"),
    ("train", [0.0, 0.0, 1.0], r"train.cartesian has shape \(3,\), expected one \[x, y, z\] a light"),
    ("unseen", [[0.0, 0.0, 1.0], [2.0, 0.0, 0.0]],
     r"unseen.cartesian\[1\] = \[2.0, 0.0, 0.0\] is not a unit direction"),
    ("train", [[float("nan"), 0.0, 1.0]], r"train.cartesian\[0\] = \[nan, 0.0, 1.0\] is not a unit direction"),
    ("train", [], r"no training lights"),
])
def test_a_light_file_edited_by_hand_is_named(tmp_path, key, rows, said):
    """lights.json as the `lights` job writes it reads back; rows that are no unit directions, flat or of another
    length (read as other lights before), or no training light at all, are one LightError naming the file."""
    main(["lights", "--sphere", "60", "--count", "4", "--unseen", "2", "--center", "0", "0", "1", "--out",
          str(tmp_path / "lights.json")])
    assert read_lights(tmp_path / "lights.json")["unseen"].shape == (2, 3)
    raw = json.loads((tmp_path / "lights.json").read_text())
    raw[key]["cartesian"] = rows
    (tmp_path / "edited.json").write_text(json.dumps(raw))
    with pytest.raises(LightError, match=rf"^\S*edited.json: {said}"):
        read_lights(tmp_path / "edited.json")


def test_cli_writes_json(tmp_path):
    out = tmp_path / "lights.json"
    main(["lights", "--sphere", "300", "--count", "40", "--unseen", "7", "--center", "0", "1", "1",
          "--out", str(out)])
    raw = json.loads(out.read_text())
    assert len(raw["train"]["cartesian"]) == 40 and len(raw["unseen"]["spherical"]) == 7
    lights = read_lights(out)
    theta, phi = np.asarray(raw["train"]["spherical"]).T
    back = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    np.testing.assert_allclose(back, lights["train"], atol=1e-12)
    assert make_light_sets(300, 40, (0, 1, 1), 7) == raw


@pytest.mark.parametrize("draw", ["training_pool", "validation_lights"])
def test_pool_and_validation_lights_lie_in_the_cap_apart_from_the_unseen_set(draw):
    import diffshadow.lights as lights

    train = cap_lights(100)
    drawn = getattr(lights, draw)(train, CAP_CENTER, 64, seed=3)
    assert drawn.shape == (64, 3)
    assert_in_cap_apart(drawn, train)
    unseen = unseen_directions(train, CAP_CENTER, 16, seed=3)  # the test set of the same seed: other lights
    assert (drawn @ unseen.T).max() < 1 - 1e-9
    np.testing.assert_array_equal(drawn, getattr(lights, draw)(train, CAP_CENTER, 64, seed=3))
    assert getattr(lights, draw)(train, CAP_CENTER, 0, seed=3).shape == (0, 3)


def test_validation_lights_are_not_pool_lights():
    from diffshadow.lights import training_pool, validation_lights

    train = cap_lights(100)
    val, pool = validation_lights(train, CAP_CENTER, 16, seed=3), training_pool(train, CAP_CENTER, 512, seed=3)
    assert (val @ pool.T).max() < 1 - 1e-9


def test_blend_weights_sum_to_one_and_favour_the_closest():
    from diffshadow.lights import blend_weights

    train = fibonacci_sphere(40)[:12]
    q = train[[2, 5]] * 0.9 + train[[3, 6]] * 0.1
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    idx, w = blend_weights(train, q, 4, "inverse-angle")
    assert np.allclose(w.sum(1), 1) and (w > 0).all()
    assert idx[:, 0].tolist() == [2, 5] and (w[:, 0] == w.max(1)).all()
    idx, w = blend_weights(train, train[[7]], 3, "inverse-angle")  # on a training light: (almost) all its own weight
    assert idx[0, 0] == 7 and w[0, 0] > 1 - 1e-5


@pytest.mark.parametrize("count,size", [(32, 50), (32, 16), (50, 50), (101, 10), (400, 50)])
def test_light_subsets_partition_the_lights_into_full_subsets(count, size):
    from diffshadow.lights import light_subsets, n_subsets, subset_indices

    train = fibonacci_sphere(1600)[select_region(fibonacci_sphere(1600), [0, 0, 1], count)]
    groups = light_subsets(train, size)
    assert len(groups) == n_subsets(count, size)
    assert sorted(i for g in groups for i in g) == list(range(count))
    assert [len(g) for g in groups[:-1]] == [size] * (len(groups) - 1) and 1 <= len(groups[-1]) <= size
    assert all(g == sorted(g) for g in groups)
    assert [subset_indices(train, size, s) for s in range(len(groups))] == groups
    if count <= size:  # one subset: every light in order (the tiny runs' single job is unchanged)
        assert groups == [list(range(count))]


def test_light_subsets_keep_a_pool_lights_neighbours_together():
    """The blend loss couples a subset's lights: a pool light's 4 nearest training lights should lie in the
    subset that takes it (its nearest light's). Runs of consecutive indices are rings around the centre and
    manage that for about 1 pool light in 10 at 400 lights in subsets of 50; compact patches for most."""
    from diffshadow.lights import blend_weights, light_subsets, training_pool

    sphere = fibonacci_sphere(1600)
    train = sphere[select_region(sphere, [0, 0, 1], 400)]
    pool = training_pool(train, [0, 0, 1], 2048, seed=1)
    nearest4 = blend_weights(train, pool, 4, "inverse-angle")[0]

    def together(groups):
        owner = np.empty(len(train), dtype=int)
        for s, g in enumerate(groups):
            owner[g] = s
        return float((owner[nearest4] == owner[nearest4[:, :1]]).all(axis=1).mean())

    rings = [list(range(s, s + 50)) for s in range(0, 400, 50)]
    assert together(rings) < 0.2
    assert together(light_subsets(train, 50)) > 0.6


def test_a_blend_across_subsets_is_one_whose_weighted_lights_lie_in_two():
    from diffshadow.lights import across_subsets, blend_weights, light_subsets, training_pool

    sphere = fibonacci_sphere(1600)
    train = sphere[select_region(sphere, [0, 0, 1], 100)]
    owner = np.empty(100, dtype=int)
    for s, g in enumerate(light_subsets(train, 50)):
        owner[g] = s
    query = training_pool(train, [0, 0, 1], 500, seed=3)
    idx, mix = blend_weights(train, query, 4, "triangle")
    across = across_subsets(train, idx, mix, 50)
    owners = [{owner[i] for i, w in zip(r, m, strict=True) if w > 1e-6} for r, m in zip(idx, mix, strict=True)]
    assert across.tolist() == [len(o) > 1 for o in owners]
    assert 0 < across.sum() < len(query) / 2  # the seam is a line through the cap
    assert not across_subsets(train, idx, mix, 100).any()  # one subset
    on_lights = blend_weights(train, train, 4, "triangle")  # a training light's blend: itself alone
    assert not across_subsets(train, *on_lights, 50).any()


def test_subset_out_of_range_and_bad_size_are_named():
    from diffshadow.lights import index_ranges, subset_indices

    train = fibonacci_sphere(40)
    with pytest.raises(ValueError, match=r"subset 4 does not exist: 40 lights in subsets of 10 give subsets 0\.\.3"):
        subset_indices(train, 10, 4)
    with pytest.raises(ValueError, match="subset_size must be >= 1, got 0"):
        subset_indices(train, 0, 0)
    assert index_ranges([0, 1, 2, 5, 7, 8]) == "0-2, 5, 7-8"


def test_nearest_and_pool_draws_in_blocks_give_the_same_bytes(monkeypatch):
    import diffshadow.lights as lights

    sphere = fibonacci_sphere(400)
    train = sphere[select_region(sphere, [0, 0, 1], 100)]
    whole = lights.nearest(train, sphere, 4), lights.training_pool(train, [0, 0, 1], 300, seed=3)
    monkeypatch.setattr(lights, "BLOCK_PAIRS", 700)  # blocks of 7 rows
    blocked = lights.nearest(train, sphere, 4), lights.training_pool(train, [0, 0, 1], 300, seed=3)
    assert all(np.array_equal(a, b) for a, b in zip(whole[0], blocked[0], strict=True))
    assert np.array_equal(whole[1], blocked[1])


@pytest.mark.parametrize("n, k", [(40, 4), (5, 5), (9, 1), (3, 4)])
def test_nearest_is_a_stable_sort_of_the_angles(n, k):
    """`nearest` partitions instead of sorting whole rows: its k columns are those of a stable argsort of the
    angle (ties by training index), with exact ties on purpose (repeated training directions, queries on them).
    Fewer training lights than k give all of them (a run of 3 lights blends its pool lights' targets from 3)."""
    from diffshadow.lights import nearest

    rng = np.random.default_rng(n)
    train = rng.normal(size=(n, 3))
    train[1::2] = train[0::2][: n // 2]
    train /= np.linalg.norm(train, axis=1, keepdims=True)
    query = np.concatenate([train[:3], rng.normal(size=(200, 3))])
    query /= np.linalg.norm(query, axis=1, keepdims=True)
    cos = np.clip((query[:, None, :] * train[None, :, :]).sum(axis=-1), -1, 1)
    expected = np.argsort(-cos, axis=1, kind="stable")[:, :min(k, n)]
    idx, angles = nearest(train, query, k)
    assert np.array_equal(idx, expected)
    assert np.array_equal(angles, np.arccos(np.take_along_axis(cos, expected, axis=1)))
    assert idx[0, 0] == 0 and idx[1, 0] == 0  # query 1 = train 1 = train 0: the tie goes to the lower index


def test_triangle_weights_reproduce_the_light_and_a_training_light_gets_its_own():
    """Inside the training lights' hull the barycentric weights sum to 1, are >= 0, and the weighted corners point
    exactly at the light; at a training light its own weight is (to rounding) 1."""
    from diffshadow.lights import Triangulation, validation_lights

    train = cap_lights(60)
    tri = Triangulation(train)
    assert len(tri.points) == len(train) + 1  # a cap: the antipode of the lights' mean closes the hull
    q = validation_lights(train, CAP_CENTER, 200, seed=4)
    idx, w = tri.weights(q)
    assert idx.shape == w.shape == (200, 3) and np.allclose(w.sum(1), 1) and (w >= 0).all()
    rim = (w == 0).any(axis=1)  # past the rim: two rim lights
    made = (train[idx] * w[..., None]).sum(1)
    made /= np.linalg.norm(made, axis=1, keepdims=True)
    assert np.allclose(made[~rim], q[~rim], atol=1e-12) and (~rim).sum() > 100
    idx, w = tri.weights(train)
    assert (idx[np.arange(len(train)), w.argmax(1)] == np.arange(len(train))).all() and w.max(1).min() > 1 - 1e-12


def test_triangle_weights_do_not_depend_on_the_lights_order():
    from diffshadow.lights import Triangulation

    train = cap_lights(40)
    q = fibonacci_sphere(50)[:10]
    perm = np.random.default_rng(0).permutation(len(train))
    a_idx, a_w = Triangulation(train).weights(q)
    b_idx, b_w = Triangulation(train[perm]).weights(q)
    for i in range(len(q)):  # the same lights with the same weights, whatever order they are listed in
        a = sorted(zip(a_idx[i].tolist(), a_w[i].round(12).tolist(), strict=True))
        b = sorted(zip(perm[b_idx[i]].tolist(), b_w[i].round(12).tolist(), strict=True))
        assert [x for x in a if x[1] > 0] == [x for x in b if x[1] > 0]


def test_triangle_weights_on_the_whole_sphere_and_with_too_few_lights():
    from diffshadow.lights import Triangulation, blend_weights

    sphere = fibonacci_sphere(100)
    tri = Triangulation(sphere)
    assert len(tri.points) == 100  # the lights surround the origin: no extra point
    q = fibonacci_sphere(333)
    idx, w = tri.weights(q)
    made = (sphere[idx] * w[..., None]).sum(1)
    assert np.allclose(made / np.linalg.norm(made, axis=1, keepdims=True), q, atol=1e-12)
    for n in (1, 2):  # no triangle: the nearest with inverse-angle weights
        idx, w = Triangulation(sphere[:n]).weights(q[:4])
        near, nw = blend_weights(sphere[:n], q[:4], n, "inverse-angle")
        assert np.array_equal(idx, near) and np.array_equal(w, nw)


def _every_face(tri, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The face that holds each query found by testing every face (the first with the largest smallest barycentric
    coordinate), and the query's coordinates in it, summed x, y, z in order as the class sums them."""
    coords = sum(query[:, None, None, i] * tri.cross[None, ..., i] for i in range(3)) / tri.det[None, :, None]
    face = np.argmax(coords.min(axis=2), axis=1)
    return face, coords[np.arange(len(query)), face]


@pytest.mark.parametrize("lights", ["sphere", "cap", "rim", "hemisphere", "ring"])
def test_triangle_weights_take_the_face_that_testing_every_face_takes(lights):
    """`Triangulation.holding` tests only the faces whose circumscribed cap holds the query, yet picks the face
    (ties: the first) and the coordinates that testing every face picks, to the bit: for directions all over the
    sphere, on the training lights, on their edges' midpoints, at faces' centres, and for a query not of length 1."""
    from diffshadow.lights import Triangulation

    train = {"sphere": lambda: fibonacci_sphere(300), "cap": lambda: cap_lights(200),
             "rim": lambda: np.asarray(make_light_sets(1600, 400, CAP_CENTER, 0)["train"]["cartesian"]),
             "hemisphere": lambda: fibonacci_sphere(600)[select_region(fibonacci_sphere(600), [0.0, 0.0, 1.0], 300)],
             "ring": lambda: _ring_with_a_light_near_the_rim(0.3)}[lights]()
    tri = Triangulation(train)
    corners = tri.points[tri.faces]
    query = np.vstack([fibonacci_sphere(20000), train, (corners + np.roll(corners, 1, axis=1)).reshape(-1, 3),
                       corners.sum(axis=1)])
    query /= np.linalg.norm(query, axis=1, keepdims=True)
    query[-1] *= 7.5
    face, coords = tri.holding(query)
    want_face, want_coords = _every_face(tri, query)
    assert np.array_equal(face, want_face)
    assert coords.tobytes() == want_coords.tobytes()
    none = tri.weights(np.zeros((0, 3)))  # no query (`lights.unseen: 0`)
    assert none[0].shape == none[1].shape == (0, 3) and none[0].dtype == np.int64


def test_a_blend_query_that_is_no_direction_is_named():
    from diffshadow.lights import Triangulation

    with pytest.raises(LightError, match=r"^blend query 1: expected a finite nonzero direction, got \[0.0, 0.0, 0.0\]"):
        Triangulation(cap_lights(20)).weights(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]))


def _ring_with_a_light_near_the_rim(inset_deg: float) -> np.ndarray:
    """A centre light, 8 lights 20 degrees around it, and one more on the rim chord between two of them, `inset_deg`
    inside it (the way a cap's outermost Fibonacci lights sit nearly on a circle)."""
    from diffshadow.lights import as_direction

    c = as_direction(CAP_CENTER)
    u = np.cross(c, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(c, u)

    def at(radius_deg: float, azimuth_deg: float) -> np.ndarray:
        r, a = np.radians(radius_deg), np.radians(azimuth_deg)
        return np.cos(r) * c + np.sin(r) * (np.cos(a) * u + np.sin(a) * v)

    ring = [at(20.0, 45.0 * i) for i in range(8)]
    mid = ring[0] + ring[1]
    mid /= np.linalg.norm(mid)  # on the rim edge between ring lights 0 and 1, 18.5 degrees from the centre
    rim_radius = np.degrees(np.arccos(mid @ c))
    return np.array([c, *ring, at(rim_radius - inset_deg, 22.5)])


def test_a_light_just_inside_the_rim_joins_it():
    """A light just inside a rim edge (the angle opposite the edge about 170 degrees) joins the rim: a light just
    past the rim beside it takes it (the convex hull's rim edge alone would give it none), and the faces still tile
    the sphere: every direction lies in exactly one. A light well inside (its angle under RIM_SLIVER_DEG) does not."""
    from diffshadow.lights import RIM_SLIVER_DEG, Triangulation, as_direction

    def opposite_deg(train: np.ndarray) -> float:
        a, b = train[1] - train[-1], train[2] - train[-1]
        return float(np.degrees(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b))))

    train = _ring_with_a_light_near_the_rim(0.3)
    near = train[-1]
    assert opposite_deg(train) > RIM_SLIVER_DEG
    c = as_direction(CAP_CENTER)
    outward = near - (near @ c) * c
    past = np.cos(np.radians(0.6)) * near + np.sin(np.radians(0.6)) * outward / np.linalg.norm(outward)
    tri = Triangulation(train)
    idx, w = tri.weights(past[None])
    assert dict(zip(idx[0].tolist(), w[0].tolist(), strict=True)).get(len(train) - 1, 0.0) > 0.99
    q = fibonacci_sphere(5000)
    coords = (q[:, None, None, :] * tri.cross[None]).sum(-1) / tri.det[None, :, None]
    holding = (coords.min(axis=2) > 1e-9).sum(axis=1)
    assert holding.max() == 1 and (holding == 1).mean() > 0.99  # none in two faces; the rest lie on an edge
    inside = _ring_with_a_light_near_the_rim(4.0)
    assert 90 < opposite_deg(inside) < RIM_SLIVER_DEG
    idx, w = Triangulation(inside).weights(past[None])
    assert sorted(idx[0][w[0] > 0].tolist()) == [1, 2]  # the rim edge's two lights


def test_an_unknown_blend_weighting_is_named():
    from diffshadow.lights import LightError, blend_weights

    with pytest.raises(LightError, match=r"^evaluate.blend_weights: expected one of triangle, inverse-angle, got "
                       r"'nearest'$"):
        blend_weights(cap_lights(8), cap_lights(8)[:1], 4, "nearest")


def test_triangle_weights_move_continuously_with_the_light():
    """Along a path from the cap's centre out past its rim, each training light's weight changes by at most a few
    times the step over the lights' spacing: no jump where the light crosses an edge or the rim (the k nearest
    with inverse-angle weights jump where the k-th nearest changes)."""
    from diffshadow.lights import LightRegion, Triangulation, blend_weights

    train = cap_lights(60)
    region = LightRegion.of(train)
    c = np.asarray(region.center)
    side = np.cross(c, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    angles = np.radians(np.linspace(0, region.radius_deg + 2 * region.spacing_deg, 4000))
    path = np.cos(angles)[:, None] * c + np.sin(angles)[:, None] * side
    step = np.radians(region.radius_deg + 2 * region.spacing_deg) / 3999 / np.radians(region.spacing_deg)

    def dense(idx, w):
        out = np.zeros((len(path), len(train)))
        np.add.at(out, (np.repeat(np.arange(len(path)), idx.shape[1]), idx.ravel()), w.ravel())
        return out

    jump = np.abs(np.diff(dense(*Triangulation(train).weights(path)), axis=0)).max()
    assert jump < 20 * step
    assert np.abs(np.diff(dense(*blend_weights(train, path, 4, "inverse-angle")), axis=0)).max() > 20 * step


@pytest.mark.parametrize("sphere, count", [(400, 32), (1600, 32), (512, 128), (8000, 2000)])
def test_the_rim_layout_moves_the_outer_shell_onto_the_caps_edge_and_keeps_count_and_cap(sphere, count):
    """lights.layout rim: as many lights as the Fibonacci region, the same cap (so unseen lights are drawn from
    the same region), the interior the region's own nearest directions, and the outer shell evenly spaced on the
    cap's edge, a spacing apart."""
    from diffshadow.lights import rim_layout

    c = np.array([0.0, 0.0, 1.0])
    cap = make_light_sets(sphere, count, c, 8, layout="cap")
    rim = make_light_sets(sphere, count, c, 8, layout="rim")
    a, b = np.asarray(cap["train"]["cartesian"]), np.asarray(rim["train"]["cartesian"])
    k = rim["on_edge"]
    assert len(b) == count and "layout" not in cap and rim["layout"] == "rim" and 3 <= k < count
    edge = np.arccos(a @ c).max()
    np.testing.assert_allclose(np.arccos(np.clip(b[-k:] @ c, -1, 1)), edge, atol=1e-9)  # on the edge
    np.testing.assert_array_equal(b[:-k], a[:-k])  # the interior: the region's own nearest directions
    assert rim["train"]["sphere_index"][-k:] == [-1] * k and rim["train"]["sphere_index"][:-k] == \
        cap["train"]["sphere_index"][:-k]
    azimuth = np.sort(np.arctan2(b[-k:, 1], b[-k:, 0]))
    np.testing.assert_allclose(np.diff(azimuth), 2 * np.pi / k, atol=1e-9)  # evenly spaced
    spacing = np.sqrt(4 * np.pi / sphere)
    assert 0.8 < 2 * np.pi * np.sin(edge) / k / spacing < 1.25  # the edge's lights a spacing apart, as inside
    assert np.arccos(np.clip(rim_layout(a, c)[0] @ c, -1, 1)).max() == pytest.approx(edge)
    held = np.asarray(rim["unseen"]["cartesian"])
    assert np.arccos(np.clip(held @ c, -1, 1)).max() <= edge + 1e-12  # drawn from the same cap


def test_the_rim_layouts_hull_holds_the_cap_to_its_polygons_incircle():
    """Every direction nearer the centre than the edge's regular k-gon's inscribed circle (atan(tan R cos(pi/k))
    on the sphere) lies inside the training lights' hull: the triangle blend takes three lights there. In the
    Fibonacci region (cap layout) a fifth of the cap lies past the hull's rim, where it takes two."""
    from diffshadow.lights import blend_weights

    c = np.array([0.0, 0.0, 1.0])
    past = {}
    for layout in ("cap", "rim"):
        sets = make_light_sets(400, 32, c, 0, layout=layout)
        train = np.asarray(sets["train"]["cartesian"])
        probe = unseen_directions(train, c, 2000, seed=5)
        _, w = blend_weights(train, probe, 4, "triangle")
        outside = (w > 1e-9).sum(axis=1) <= 2
        past[layout] = outside.mean()
        if layout == "rim":
            edge, k = np.arccos(train[-1] @ c), sets["on_edge"]
            incircle = np.arctan(np.tan(edge) * np.cos(np.pi / k))
            assert not outside[np.arccos(np.clip(probe @ c, -1, 1)) < incircle - 1e-6].any()
    assert past["cap"] > 0.15 and past["rim"] < 0.5 * past["cap"]


def test_the_rim_layout_of_three_lights_or_fewer_is_the_region_and_a_bad_layout_is_named():
    for count in (1, 3):
        assert make_light_sets(100, count, (0, 0, 1), 2, layout="rim")["train"] == \
            make_light_sets(100, count, (0, 0, 1), 2, layout="cap")["train"]
    with pytest.raises(LightError, match=r"^layout: expected one of rim, cap, got 'ring'$"):
        make_light_sets(100, 10, (0, 0, 1), 2, layout="ring")
