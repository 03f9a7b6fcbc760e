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
