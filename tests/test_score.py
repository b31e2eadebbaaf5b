"""cfx score: a haircut scored against a target from four views (hair silhouette IoU) and by strand length."""

import numpy as np
import pytest
from PIL import Image

from io_usd.cache import CacheWriter
from io_usd.score import (
    BOTH,
    RESULT_ONLY,
    TARGET_ONLY,
    VIEWS,
    length_agreement,
    score_caches,
    strand_roots_and_lengths,
)
from sim.cli import main
from sim.hairstyle import HairstyleParams, grow_hairstyle, sample_scalp
from sim.head import procedural_head

SIZE = (160, 160)
STRANDS, VERTS = 120, 12


def _write(path, head, strands=None, frames=(1,)):
    """A cache with the head as collider and `strands` (S, V, 3) as one hair prim (None: no hair)."""
    with CacheWriter(path, fps=24, start_frame=frames[0], end_frame=frames[-1]) as w:
        w.add_mesh("head", "collider", head.vertices, head.faces, color=(0.8, 0.65, 0.55))
        if strands is not None:
            w.add_curves("hair", "hair", np.full(len(strands), strands.shape[1]),
                         np.full(strands.shape[0] * strands.shape[1], 1e-4))
        for f in frames:
            w.write_frame(f, {"head": head.vertices, **({"hair": strands.reshape(-1, 3)} if strands is not None else {})})
    return str(path)


def _rotate_about_y(points, degrees):
    a = np.radians(degrees)
    m = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    return points @ m.T


@pytest.fixture(scope="module")
def caches(tmp_path_factory):
    """The target groom (straight strands, evenly spaced vertices) and variations of it."""
    folder = tmp_path_factory.mktemp("score")
    head = procedural_head(rings=40, segments=32)
    roots, _, _, normals = sample_scalp(head.vertices, head.faces, head.scalp_faces, STRANDS, seed=3)
    points, _, _ = grow_hairstyle(HairstyleParams(style="straight", vertices=VERTS, length=0.2), roots, normals,
                                  lambda p, margin: p, axis_point=(0.0, 0.35, 0.0))
    strands = points.reshape(STRANDS, VERTS, 3)
    front = strands[strands[:, 0, 2] > 0.02]
    back = roots[:, 2] < -0.06
    tuft = roots[back][:, None, :] + np.linspace(0.0, 0.03, 4)[None, :, None] * np.array([0.0, -0.6, -0.8])
    return {
        "target": _write(folder / "target.usdc", head, strands),
        "cut": _write(folder / "cut.usdc", head, strands[:, :VERTS // 2]),  # the tip half of every strand cut off
        "half": _write(folder / "half.usdc", head, strands[:, :1] + 0.5 * (strands - strands[:, :1])),
        "shifted": _write(folder / "shifted.usdc", head, strands + [0.001, 0.0, 0.0]),
        "rotated": _write(folder / "rotated.usdc", head, _rotate_about_y(strands, 20.0)),
        "front": _write(folder / "front.usdc", head, front[:, :4]),
        "front_and_back": _write(folder / "front_and_back.usdc", head, np.concatenate([front[:, :4], tuft])),
        "bald": _write(folder / "bald.usdc", head),
        "folder": folder,
    }


def test_a_cache_scored_against_itself_is_perfect_and_the_report_is_written(caches, capsys):
    report = score_caches(caches["target"], caches["target"], size=SIZE, images=False)
    assert report.score == 100.0 and report.length_agreement == 1.0 and report.matched_fraction == 1.0
    assert [v.name for v in report.views] == [name for name, _ in VIEWS] == ["front", "left", "right", "back"]
    assert all(v.iou == 1.0 and v.result_mask.sum() > 200 for v in report.views)  # hair seen from every side

    png = caches["folder"] / "self.png"
    assert main(["score", caches["target"], caches["target"], "-o", str(png), "--size", "160x160", "-q"]) == 0
    out = capsys.readouterr().out
    assert "score 100.0 / 100" in out and out.count(" 1.000") >= 6  # four views, the mean, length agreement
    sheet = Image.open(png)
    assert sheet.width == 4 * SIZE[0] and sheet.height > 3 * SIZE[1]  # a column per view; result, target, difference


def test_a_shorter_cut_scores_worse_against_the_uncut_target_than_against_itself(caches):
    report = score_caches(caches["cut"], caches["target"], size=SIZE, images=False)
    # the cut keeps 6 of 12 evenly spaced vertices: 5 of 11 segments
    assert report.length_agreement == pytest.approx(5 / 11, abs=0.01) and report.matched_fraction == 1.0
    assert all(v.iou < 0.85 for v in report.views)  # the lost tips show from every side
    assert report.score < 40.0
    assert report.score == pytest.approx(100.0 * report.mean_iou * report.length_agreement)
    for v in report.views:  # what the cut took shows as target-only (blue); the result adds (almost) nothing
        difference = v.difference().reshape(-1, 3)
        missing = np.all(difference == TARGET_ONLY, axis=1).sum()
        extra = np.all(difference == RESULT_ONLY, axis=1).sum()
        assert missing > 20 * max(extra, 1) and np.all(difference == BOTH, axis=1).sum() > 0


def test_moving_the_strands_scores_lower_than_leaving_them(caches):
    shifted = score_caches(caches["shifted"], caches["target"], size=SIZE, images=False)
    rotated = score_caches(caches["rotated"], caches["target"], size=SIZE, images=False)
    # 1 mm: every root still matches, the lengths agree, only the silhouettes move a little
    assert shifted.length_agreement == pytest.approx(1.0) and 80.0 < shifted.score < 100.0
    # turned 20 degrees about the head's axis: roots centimetres away match nothing (but near the axis)
    assert rotated.matched_fraction < 0.05 and rotated.score < 5.0
    assert all(r.iou < s.iou < 1.0 for r, s in zip(rotated.views, shifted.views))


def test_halving_every_strand_gives_length_agreement_one_half(caches):
    report = score_caches(caches["half"], caches["target"], size=SIZE, images=False)
    assert report.matched_fraction == 1.0
    assert report.length_agreement == pytest.approx(0.5, abs=1e-6)  # 1 - mean |L/2 - L| / L
    np.testing.assert_allclose(report.relative_length_errors, 0.5, atol=1e-6)


def test_erased_and_added_strands_count_as_fully_wrong():
    counts = np.full(4, 3)
    target = np.array([[x, 0.0, 0.0] for x in range(4) for _ in range(3)], np.float64)
    target[:, 1] = -np.tile([0.0, 0.1, 0.2], 4)  # four strands 0.2 m long, roots 1 m apart
    roots, lengths = strand_roots_and_lengths(target, counts)
    np.testing.assert_allclose(lengths, 0.2)
    # two of four strands erased: A = (1 + 1 + 0 + 0) / 4
    assert length_agreement(roots[:2], lengths[:2], roots, lengths)[:2] == (pytest.approx(0.5), 0.5)
    # every target strand matched and one added far from any target root: A = 4 / 5
    extra_roots = np.concatenate([roots, [[9.0, 0.0, 0.0]]])
    extra_lengths = np.concatenate([lengths, [0.2]])
    assert length_agreement(extra_roots, extra_lengths, roots, lengths)[:2] == (pytest.approx(0.8), 1.0)
    # a root 3 mm off is no longer the same strand; 1 mm off still is
    for offset, matched in ((0.003, 0.0), (0.001, 1.0)):
        assert length_agreement(roots + offset / np.sqrt(3), lengths, roots, lengths)[1] == matched


def test_hair_hidden_behind_the_head_does_not_count_from_the_front(caches):
    report = score_caches(caches["front_and_back"], caches["front"], size=SIZE, images=False)
    ious = report.ious
    assert ious["front"] == 1.0  # the tuft lies on the back of the head: the head hides it
    assert ious["back"] < 0.9


def test_missing_file_and_a_cache_without_hair_exit_2_naming_the_file(caches, capsys):
    missing = str(caches["folder"] / "nope.usdc")
    assert main(["score", missing, caches["target"]]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and missing in err and "no such" in err

    assert main(["score", caches["target"], caches["bald"]]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and caches["bald"] in err and "no hair prim" in err

    text = caches["folder"] / "notes.usdc"
    text.write_text("not a cache")
    assert main(["score", str(text), caches["target"]]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(text) in err and "not a USD file" in err

    assert main(["score", caches["target"], caches["target"], "--frame", "7"]) == 2
    assert "frame 7" in capsys.readouterr().err
