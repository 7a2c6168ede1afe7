"""Semantic K-means masks on synthetic feature maps with known clusters."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from edit.semantic_masks import (
    SemanticMaskConfig,
    SemanticMasks,
    fit_region_centres,
    nearest_centre_distance,
)
from render.errors import SineError

C = 12


def _basis(k: int) -> torch.Tensor:
    e = torch.zeros(C)
    e[k] = 1.0
    return e


def _feature_map(labels: np.ndarray, seed: int, noise: float = 0.02, scale: float = 3.0):
    """Features [C, H, W]: pixel with label k gets scale * (e_k + noise); label -1 is zero+noise."""
    g = torch.Generator().manual_seed(seed)
    h, w = labels.shape
    f = torch.randn(C, h, w, generator=g) * noise
    for k in np.unique(labels):
        if k >= 0:
            f[:, torch.from_numpy(labels == k)] += _basis(int(k))[:, None]
    return f * scale  # the scale must not matter: distances use normalised features


def test_mask_in_another_view_is_exactly_the_painted_part():
    # Editing view: part 0 on the left, part 1 top right, part 2 bottom right.
    lab = np.zeros((40, 48), int)
    lab[:, 24:] = 1
    lab[20:, 24:] = 2
    feats = _feature_map(lab, seed=0)
    painted = np.zeros_like(lab, bool)
    painted[5:15, 4:12] = True  # a small stroke inside part 0 only
    masks = SemanticMasks(feats, painted, SemanticMaskConfig(num_samples=300, seed=1))
    assert masks.centres.shape == (15, C)
    # All centres are (up to noise) the direction of part 0.
    assert (masks.centres[:, 0] > 0.99).all()
    assert masks.mask(feats).numpy().tolist() == (lab == 0).tolist()

    # Another view: parts moved, a new part 3 and empty background (-1).
    lab2 = np.full((30, 30), -1)
    lab2[2:12, 15:28] = 0
    lab2[15:25, 3:10] = 1
    lab2[15:25, 12:20] = 3
    lab2[26:29, :] = 0
    got = masks.mask(_feature_map(lab2, seed=5)).numpy()
    assert got.tolist() == (lab2 == 0).tolist()


def test_threshold_on_mixed_features():
    # Features mixing part 0 and part 1: normalised distance to e_0 is sqrt(2 - 2 cos).
    centres = fit_region_centres(
        _feature_map(np.zeros((10, 10), int), seed=0, noise=0.0),
        np.ones((10, 10), bool),
        SemanticMaskConfig(num_samples=50),
    )
    assert centres.shape == (1, C)  # one distinct feature: K drops to 1
    mixes = torch.stack(
        [
            0.95 * _basis(0) + 0.3122 * _basis(1),  # cos 0.95  -> d 0.316: editable
            0.85 * _basis(0) + 0.5268 * _basis(1),  # cos 0.85  -> d 0.548: background
            0.9 * _basis(0) + 0.4359 * _basis(1),  # cos 0.9   -> d 0.447: editable
            _basis(1),  # cos 0 -> d 1.414
        ],
        dim=1,
    )[:, None]  # [C, 1, 4]
    d = nearest_centre_distance(mixes * 7.0, centres)[0]
    torch.testing.assert_close(d, torch.tensor([0.3162, 0.5477, 0.4472, 1.4142]), atol=2e-3, rtol=0)
    masks = SemanticMasks(torch.zeros(C, 1, 1) + _basis(0)[:, None, None], np.ones((1, 1), bool))
    assert masks.mask(mixes).tolist() == [[True, False, True, False]]


def test_seeded_and_region_resized():
    lab = np.zeros((20, 20), int)
    lab[:, 10:] = 1
    feats = _feature_map(lab, seed=3, noise=0.05)
    region = np.zeros((40, 40), bool)  # painted at twice the feature resolution
    region[:, :20] = True
    cfg = SemanticMaskConfig(num_samples=200, num_clusters=4)
    a = fit_region_centres(feats, region, cfg)
    b = fit_region_centres(feats, region, cfg)
    torch.testing.assert_close(a, b)
    assert (a[:, 0] > 0.9).all()
    with pytest.raises(SineError, match="empty"):
        fit_region_centres(feats, np.zeros((20, 20), bool), cfg)


def test_contrast_rule_takes_faces_of_the_part_the_threshold_misses():
    # Editing view: part 0 (painted, e_0) above part 1 (e_1), the rest of the object.
    lab = np.zeros((20, 20), int)
    lab[10:] = 1
    feats = _feature_map(lab, seed=0, noise=0.0)
    painted, obj = lab == 0, np.ones_like(lab, bool)
    cfg = SemanticMaskConfig(num_samples=100, rest_margin=0)
    contrast = SemanticMasks(feats, painted, cfg, object_mask=obj)
    threshold = SemanticMasks(feats, painted, SemanticMaskConfig(num_samples=100, rule="threshold"))
    assert contrast.rule == "contrast" and threshold.rule == "threshold"
    # Another view, three pixels: an unseen face of part 0 (cos 0.8 to e_0: d 0.63 > 0.5), a
    # neighbour that is mostly part 1 but a little like part 0 (cos 0.6 to e_0, 0.8 to e_1),
    # and an unrelated part (mostly e_3, a little like part 1).
    other = torch.stack(
        [
            0.8 * _basis(0) + 0.6 * _basis(4),
            0.6 * _basis(0) + 0.8 * _basis(1),
            0.95 * _basis(3) + 0.3122 * _basis(1),
        ],
        dim=1,
    )[:, None]  # [C, 1, 3]
    assert threshold.mask(other)[0].tolist() == [False, False, False]
    assert contrast.mask(other)[0].tolist() == [True, False, False]
    # The editing view itself is exact under both rules.
    assert contrast.mask(feats).numpy().tolist() == painted.tolist()


def test_contrast_rule_falls_back_without_a_rest_of_the_object():
    lab = np.zeros((12, 12), int)
    feats = _feature_map(lab, seed=0)
    everything = np.ones_like(lab, bool)
    masks = SemanticMasks(feats, everything, SemanticMaskConfig(num_samples=50), everything)
    assert masks.rule == "threshold" and masks.other_centres is None
    assert SemanticMasks(feats, everything, SemanticMaskConfig(num_samples=50)).rule == "threshold"


def _plane_points(h: int, w: int) -> np.ndarray:
    """[h, w, 3] surface points on the plane z = 0: x from 0 to 1 across, y from 0 to 1 down."""
    x = np.linspace(0.0, 1.0, w, dtype=np.float32)[None, :].repeat(h, 0)
    y = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None].repeat(w, 1)
    return np.stack([x, y, np.zeros_like(x)], axis=-1)


def test_spatial_term_gives_a_far_look_alike_to_the_rest():
    # Editing view: part 0 (painted, e_0) on the left half of the surface (x < 0.5), part 1 on
    # the right half. Object centre (0.5, 0.5, 0), mean radius ~0.38.
    lab = np.zeros((20, 20), int)
    lab[:, 10:] = 1
    feats = _feature_map(lab, seed=0, noise=0.0)
    painted, obj, points = lab == 0, np.ones_like(lab, bool), _plane_points(20, 20)
    # Another view, three pixels: the part's unseen far side at x = 0.2 (e_0), a look-alike of
    # the part (e_0) at x = 0.95 among part 1's surface, and part 1 itself at x = 0.7.
    other = torch.stack([_basis(0), _basis(0), _basis(1)], dim=1)[:, None]  # [C, 1, 3]
    where = np.array([[[0.2, 0.5, 0.0], [0.95, 0.5, 0.0], [0.7, 0.5, 0.0]]], np.float32)

    plain = SemanticMasks(feats, painted, SemanticMaskConfig(num_samples=100, spatial=0.0), obj)
    assert plain.mask(other)[0].tolist() == [True, True, False]  # features alone: look-alike
    # Look-alike: feature distance 0 to the part vs sqrt(2) to part 1; spatial distance ~0.45 to
    # the part's nearest surface (x < 0.5), i.e. 4 * 0.45 / 0.38 ~ 4.7 > sqrt(2): the rest's.
    cfg = SemanticMaskConfig(num_samples=100, spatial=4.0, rest_margin=0)
    spatial = SemanticMasks(feats, painted, cfg, obj, points=points)
    assert spatial.centres.shape[1] == C + 3
    assert spatial.mask(other, points=where)[0].tolist() == [True, False, False]
    assert spatial.mask(feats, points=points).numpy().tolist() == painted.tolist()
    # the centres' surface points, back in run units, lie on the painted half
    feature_part, centre_points = spatial.split(spatial.centres)
    assert feature_part.shape == (len(spatial.centres), C)
    assert (centre_points[:, 0] < 0.5).all() and centre_points[:, 2].abs().max() < 1e-5
    with pytest.raises(ValueError, match="points"):
        spatial.mask(other)
    # the threshold rule has no rest to weigh positions against: features only
    rule = SemanticMaskConfig(num_samples=100, spatial=4.0, rule="threshold")
    threshold = SemanticMasks(feats, painted, rule, obj, points=points)
    assert threshold.split(threshold.centres)[1] is None
    assert threshold.mask(other)[0].tolist() == [True, True, False]


def test_guided_refinement_moves_a_blurred_edge_onto_the_image_edge():
    from edit.semantic_masks import guided_refine

    x = np.arange(40, dtype=np.float32)[None, :].repeat(40, 0)  # [40, 40] column index
    image = np.repeat((x >= 20)[..., None], 3, axis=2).astype(np.float32)  # black | white
    # a soft score like a patch-blurred feature decision: its zero crossing is 2 px off the edge
    score = torch.from_numpy(np.tanh((22.0 - x) / 4.0))
    assert (score > 0).numpy().tolist() != (x < 20).tolist()
    refined = guided_refine(score, image, np.ones((40, 40), bool), radius=0.2, eps=0.01)
    assert (refined > 0).numpy().tolist() == (x < 20).tolist()
    # no object pixels: nothing to scale the radius by, the score is returned as it is
    same = guided_refine(score, image, np.zeros((40, 40), bool), radius=0.1, eps=0.01)
    assert torch.equal(same, score)
