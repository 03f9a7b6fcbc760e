"""Stress: the whole workflow at the edges the config schema allows. Each of these once failed a job late in the
run, or wrote NaN: fewer training lights than a pool light's blend takes (4), no unseen test lights, no sampler
curve, a fine-tuning batch with fewer lights than processes, the smallest evaluation images."""

import copy
import json
import re

import pytest
from test_workflow import TINY, snakemake

pytestmark = pytest.mark.stress

EDGES = copy.deepcopy(TINY)
EDGES["lights"].update(count=3, unseen=0)  # 3 < lights.BLEND_K; nothing held out
EDGES["subset_size"] = 2  # subsets of 2 and 1
EDGES["siren"] = {"width": 1, "blocks": 1}
EDGES["data_inr"].update(width=1)
# 2 processes, batches of 2 and 1 lights: the second rank has no light in the last batch
EDGES["finetune"].update(nproc=2, batch_size=2)
EDGES["evaluate"].update(ddpm_lights=0, wide_lights=0)
EDGES["render"].update(image_size=11)


def test_a_run_at_the_schemas_edges_finishes_and_writes_no_nan(tmp_path):
    snakemake(tmp_path, config=EDGES)
    res = tmp_path / "results/nucleon"
    # logs and JSON say what is missing instead of printing or storing NaN ("nan" as a word: not "nanoseconds")
    nan = re.compile(r"\bnan\b", re.IGNORECASE)
    for path in [*res.glob("logs/*.log"), *res.glob("*.json")]:
        found = [line for line in path.read_text().splitlines() if nan.search(line)]
        assert not found, f"{path.name}: {found[:3]}"
    assert "3 training, 0 unseen" in (res / "report/summary.html").read_text()
    caches = json.loads((res / "caches.json").read_text())["caches"]
    assert caches and all("unseen_psnr" not in row for row in caches)
    finetune_log = (res / "logs/finetune_render.log").read_text()
    assert "2 process(es)" in finetune_log
