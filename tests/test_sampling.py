"""Every random draw of a run has a name in `diffshadow.sampling`: no stream number or seed offset is written as a
bare number where it is used, no two streams share a number, and no two derived seeds meet."""

import re
from pathlib import Path

import pytest

from diffshadow import sampling

PACKAGE = Path(sampling.__file__).parent
# a stream number after the seed in seeded(...), an offset added to a seed, a numpy seed list with a number in it
BARE = [re.compile(r"seeded\([^)]*,\s*-?\d"), re.compile(r"seed\s*[+-]\s*\d"), re.compile(r"seed=\[[^\]]*\d")]


def bare_draws(text: str) -> list[str]:
    return [line.strip() for line in text.splitlines() for pattern in BARE
            if pattern.search(line.split("#")[0])]


def test_no_draw_names_its_stream_or_seed_offset_by_a_bare_number():
    # bench/ draws synthetic inputs that no result depends on; sampling.py is the registry itself
    found = {str(p.relative_to(PACKAGE)): hits for p in sorted(PACKAGE.rglob("*.py"))
             if p.parent.name != "bench" and p.name != "sampling.py" and (hits := bare_draws(p.read_text()))}
    assert not found, f"name these draws in diffshadow/sampling.py: {found}"


@pytest.mark.parametrize("line", ["seed=cfg.seed + 7919)", "seeded(cfg.seed, 4, step)", "seed=[seed, 1])",
                                  "return fit.seed + 7919 * (subset + 1)"])
def test_the_scan_finds_a_bare_number(line):
    assert bare_draws(line) == [line]
    assert bare_draws(line.replace("7919", "FIT_BLEND_POOL_SEED").replace("4,", "Stream.EVAL_POINTS,")
                      .replace("1]", "LightStream.POOL]")) == []


def test_streams_and_derived_seeds_never_meet():
    for registry in (sampling.Stream, sampling.LightStream):
        assert len(registry.__members__) == len(registry), registry  # no alias: no two names for one number
    # subset k's held-out seed is fit.seed + 7919 (k + 1); the probe's fit.seed + 104729: both on Stream.HELD_OUT
    assert all(sampling.SUBSET_HELD_OUT_SEED * (k + 1) != sampling.PROBE_HELD_OUT_SEED for k in range(100_000))
    # stage 1 subsets pick pool lights from FIT_POOL_PICK - k: below every member (their points: streams 0, 1, ...
    # of fit.seed, apart from stage 1's negative members)
    members = {int(m) for m in sampling.Stream}
    assert not members & set(range(sampling.Stream.FIT_POOL_PICK - 1, sampling.Stream.FIT_POOL_PICK - 1000, -1))


def test_the_visible_voxels_found_a_slab_at_a_time_are_those_found_at_once(monkeypatch):
    """`PointSampler` reads the opacity a slab of planes at a time (the whole volume's held ~10 grids' bytes): the
    same visible voxels in the same order, so the same points, whatever the slab (one plane here), on dense, sparse
    and empty volumes."""
    import numpy as np
    import torch
    from conftest import identity_tf

    from diffshadow.volume import Volume

    rng = np.random.default_rng(7)
    for data in (rng.random((13, 9, 11)), rng.random((13, 9, 11)) * (rng.random((13, 9, 11)) < 0.05),
                 np.zeros((5, 6, 7))):
        vol = Volume(data=data.astype(np.float32), extent=np.array([1.0, 0.8, 1.2]), name="r")
        whole = sampling.PointSampler(vol, identity_tf(), 0.5)
        with monkeypatch.context() as m:
            import diffshadow.volume as volume

            m.setattr(volume, "SLAB_VOXELS", 1)
            slabs = sampling.PointSampler(vol, identity_tf(), 0.5)
        expected = torch.nonzero(torch.as_tensor(data) > 0).flip(1).float() * whole.voxel
        assert torch.equal(whole.visible, expected) and torch.equal(slabs.visible, expected)
        g = [torch.Generator().manual_seed(3) for _ in range(2)]
        assert torch.equal(whole.sample(2, 64, g[0]), slabs.sample(2, 64, g[1]))
