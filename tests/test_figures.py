"""The report's point labels (`report.label_points`): each beside its own point, none over another, none outside
the axes, wherever there is room; a crowd too dense for that still gets every label."""

import numpy as np
import pytest

from diffshadow.report import LABEL_PLACES, label_points, pyplot


def _labelled(points: list[tuple[float, float]], labels: list[str], size=(5, 4)):
    fig, ax = pyplot().subplots(figsize=size)
    xy = np.asarray(points, dtype=float)
    ax.scatter(xy[:, 0], xy[:, 1], s=36)
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 10)
    fig.tight_layout()
    boxes = label_points(ax, points, labels)
    return fig, ax, boxes


def test_a_crowd_with_room_around_it_gets_labels_that_do_not_overlap():
    # a tight cluster (the caches figure's best caches at 512 lights) in an axes with room around it
    points = [(5.0, 5.0), (5.2, 5.05), (5.1, 4.9), (4.9, 5.1), (5.3, 4.95), (5.05, 5.2), (4.95, 4.85)]
    labels = ["SIRENs fp32", "fp16", "mix 0.4, fp16", "mix 0.4, fp32", "model fp16", "model fp32", "basis-256"]
    fig, ax, boxes = _labelled(points, labels)
    frame = ax.get_window_extent(fig.canvas.get_renderer())
    assert len(boxes) == len(labels) == len(ax.texts)
    for i, a in enumerate(boxes):
        assert frame.x0 <= a.x0 and a.x1 <= frame.x1 and frame.y0 <= a.y0 and a.y1 <= frame.y1, labels[i]
        for j, b in enumerate(boxes[:i]):
            assert not a.overlaps(b), (labels[i], labels[j])
    # each label names its own point: its annotation points at it
    assert [t.xy for t in ax.texts] == points
    fig.clf()


def test_a_lone_point_is_labelled_at_the_first_place_up_and_to_the_right():
    fig, ax, _ = _labelled([(5.0, 5.0)], ["alone"])
    (note,) = ax.texts
    dx, dy, ha, va = LABEL_PLACES[0]
    assert note.xyann == (dx, dy) and (note.get_ha(), note.get_va()) == (ha, va) == ("left", "bottom")
    assert note.arrow_patch is None  # near its point: no leader line
    fig.clf()


def test_a_crowd_with_no_room_still_labels_every_point():
    points = [(5.0 + 0.01 * i, 5.0) for i in range(40)]
    fig, ax, boxes = _labelled(points, [f"cache {i}" for i in range(40)], size=(2, 1.5))
    assert len(boxes) == 40 == len(ax.texts)
    fig.clf()


def test_labels_and_points_must_pair():
    fig, ax = pyplot().subplots()
    with pytest.raises(ValueError):
        label_points(ax, [(0.0, 0.0), (1.0, 1.0)], ["one"])
    fig.clf()


def test_the_image_grid_shows_every_row_of_a_small_run_and_a_few_lights_spread_over_a_large_one():
    """`grid_rows`: the default run's 2 lights x 2 views a set all, in light order (10 after 2); 32 lights x 2 views
    a set GRID_ROWS_PER_SET each, the naive baseline's row kept, the rest spread from the first light to the last
    and alternating views."""
    from diffshadow.report import GRID_ROWS_PER_SET, grid_rows

    small = [f"{s}{i}_view{v}" for s in ("unseen", "train") for i in (10, 2) for v in (1, 0)]
    assert grid_rows(small) == [f"{s}{i}_view{v}" for s in ("train", "unseen") for i in (2, 10) for v in (0, 1)]
    large = [f"{s}{i}_view{v}" for s in ("train", "unseen") for i in range(0, 64, 2) for v in (0, 1)]
    shown = grid_rows(large, keep={"train30_view0"})
    train, unseen = shown[:GRID_ROWS_PER_SET], shown[GRID_ROWS_PER_SET:]
    assert len(unseen) == GRID_ROWS_PER_SET and all(t.startswith("unseen") for t in unseen)
    assert "train30_view0" in train and len({t.split("_")[0] for t in train}) == GRID_ROWS_PER_SET
    assert unseen[0].startswith("unseen0_") and unseen[-1].startswith("unseen62_")
    assert {t[-1] for t in unseen} == {"0", "1"}
    assert [int(t[6:].split("_")[0]) for t in unseen] == sorted(int(t[6:].split("_")[0]) for t in unseen)


def test_a_large_runs_image_grid_stays_a_page_and_says_how_many_it_leaves_out(tmp_path, monkeypatch):
    """32 lights x 2 views a set render 128 rows of images; the figure shows 2 x GRID_ROWS_PER_SET of them, as high
    as the default run's figure, and says so in its title."""
    from PIL import Image

    import diffshadow.report as report
    from diffshadow.report import GRID_ROWS_PER_SET, image_grid_figure

    titles, save = [], report.save_figure
    monkeypatch.setattr(report, "save_figure", lambda path, fig: (titles.append(fig.get_suptitle()), save(path, fig)))

    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(0)
    tags = [f"{s}{i}_view{v}" for s in ("train", "unseen") for i in range(32) for v in (0, 1)]
    for tag in tags:
        for mode in ("gt", "inr_generated", "noshadow") + (("naive",) if tag == "train0_view0" else ()):
            Image.fromarray(rng.integers(0, 255, (12, 12, 3), dtype=np.uint8)).save(images / f"{tag}_{mode}.png")
    lights = {s: rng.standard_normal((32, 3)) for s in ("train", "unseen")}
    image_grid_figure(images, lights, tmp_path / "grid.png")
    assert Image.open(tmp_path / "grid.png").height == 2 * GRID_ROWS_PER_SET * 240  # 2.4 inches a row at 100 dpi
    assert titles == [f"{2 * GRID_ROWS_PER_SET} of the 128 renderings, at most {GRID_ROWS_PER_SET} a light set "
                      "(every one is in images/)"]


def test_the_image_grid_caption_states_the_figures_row_cap():
    """The report's caption (workflow/report/image_grid.rst) says how many rows a light set the figure shows: the
    figure's own GRID_ROWS_PER_SET, so that the two cannot drift apart."""
    import re
    from pathlib import Path

    from diffshadow.report import GRID_ROWS_PER_SET

    caption = (Path(__file__).parents[1] / "workflow/report/image_grid.rst").read_text()
    assert re.findall(r"at most (\d+) rows a light set", caption) == [str(GRID_ROWS_PER_SET)]
