"""Two-view stereo between neighbouring views: rectify (OpenCV), StereoSGBM, back to camera z.

For a view and a neighbour: `cv2.stereoRectify` from their relative pose, both images and masks
remapped, StereoSGBM on the rectified pair (disparity range bounded by a depth range the caller
gives, e.g. from the visual hull), a left-right consistency check (the right matcher of
`cv2.ximgproc`), disparities outside either silhouette dropped, and the result converted to
camera-z depth on the ORIGINAL view's pixel grid (each original pixel samples the rectified
disparity at its rectified position; nearest, so depth never mixes across edges).
Rectification keeps separate principal points (no CALIB_ZERO_DISPARITY): with a long lens the
zero-disparity layout would push a converging pair's object out of the overlap.
A pair displaced along the image's y (cameras rolled on their ring, portrait photos) is
rectified vertically; its images are transposed for SGBM, which searches along rows.
Pixel convention: ours puts pixel centres at +0.5, OpenCV's at integers (K shifted by 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from render.cameras import Camera


@dataclass
class StereoParams:
    """Knobs of the SGBM stereo depth."""

    block_size: int = 5
    uniqueness_ratio: int = 10
    speckle_window: int = 50
    speckle_range: int = 2
    lr_max_diff: float = 1.0  # left-right consistency, pixels
    min_angle_deg: float = 4.0  # neighbour's viewing direction differs by at least this
    max_angle_deg: float = 30.0  # ... and at most this


def _cv_K(cam: Camera) -> np.ndarray:
    K = cam.K.astype(np.float64).copy()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    return K


def neighbours(cameras: list[Camera], i: int, params: StereoParams) -> list[int]:
    """Up to two partners of view i: the nearest viewing direction on each side.

    The sides are those of the line through view i's centre, in its image plane, towards its
    nearest partner: left and right on an upright ring, up and down on a ring shot with the
    camera rolled by 90 degrees.
    """
    ci = cameras[i]
    axis_i = ci.camera_to_world[:3, 2]
    image_plane = ci.camera_to_world[:3, :2]  # [3, 2]: camera x and y in the world
    candidates = []  # (angle, j, offset of j's centre in i's image plane [2])
    for j, cj in enumerate(cameras):
        if j == i:
            continue
        cos = float(np.clip(axis_i @ cj.camera_to_world[:3, 2], -1, 1))
        angle = float(np.degrees(np.arccos(cos)))
        if params.min_angle_deg <= angle <= params.max_angle_deg:
            candidates.append((angle, j, (cj.center - ci.center) @ image_plane))
    if not candidates:
        return []
    candidates.sort(key=lambda c: c[0])
    _, nearest, direction = candidates[0]
    opposite = [j for _, j, offset in candidates[1:] if offset @ direction < 0]
    return [nearest, *opposite[:1]]


def _gray(image: np.ndarray) -> np.ndarray:
    """float RGB [H, W, 3] in [0, 1] -> uint8 gray [H, W]."""
    u8 = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY)


def pair_depth(
    cam_a: Camera,
    cam_b: Camera,
    image_a: np.ndarray,
    image_b: np.ndarray,
    mask_a: np.ndarray,
    mask_b: np.ndarray,
    z_range: tuple[float, float],
    params: StereoParams | None = None,
) -> np.ndarray:
    """Camera-z depth [H, W] of view a from the pair (a, b); 0 where stereo has no answer.

    `z_range` = (near, far) camera-z bounds of the object in view a (sets the disparity range).
    """
    params = params or StereoParams()
    h, w = image_a.shape[:2]
    size = (w, h)
    rel = cam_b.world_to_camera @ cam_a.camera_to_world  # x_b = R x_a + T
    R, T = rel[:3, :3].copy(), rel[:3, 3].reshape(3, 1).copy()
    Ka, Kb = _cv_K(cam_a), _cv_K(cam_b)
    zero = np.zeros((1, 5))
    # no CALIB_ZERO_DISPARITY: each rectified image keeps its own principal point, so a converging
    # pair (both cameras look at the object) sees it near the same place: small disparities.
    R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(Ka, zero, Kb, zero, size, R, T, flags=0, alpha=-1)
    # a pair displaced mostly along the image's y (a ring shot with the camera rolled, portrait
    # photos) is rectified vertically: its images are transposed for SGBM, which searches rows.
    vertical = abs(P2[1, 3]) > abs(P2[0, 3])
    ax = 1 if vertical else 0  # the rectified axis along which disparities lie
    span = h if vertical else w  # image length along that axis
    f_rect = float(P1[ax, ax])
    baseline = float(-P2[ax, 3] / P2[ax, ax])  # > 0: b lies towards +x (+y) of a, rectified
    flip = baseline < 0  # mirror both images so that a is the left image for SGBM
    baseline = abs(baseline)
    # SGBM disparity d = f B / z + offset (x_a - x_b = f B / z + (cx_a - cx_b), mirrored: negated)
    offset = float(P1[ax, 2] - P2[ax, 2]) * (-1.0 if flip else 1.0)
    if not (np.isfinite(f_rect) and f_rect > 0 and baseline > 0):
        return np.zeros((h, w), np.float32)
    # disparity range from the depth range: a point at camera-a depth z on the ray of pixel p
    # lies at rectified depth z (R1 K^-1 p)_z, extreme at the image's corners; 2 px of margin.
    near, far = z_range
    corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], np.float64)
    rect_z = corners @ np.linalg.inv(Ka).T @ R1[2]  # [4] rectified z per unit camera-a z
    if rect_z.min() <= 0:
        return np.zeros((h, w), np.float32)
    d_min = f_rect * baseline / (far * rect_z.max()) + offset - 2.0
    d_max = f_rect * baseline / max(near * rect_z.min(), 1e-9) + offset + 2.0
    # keep SGBM's disparities positive (its sub-pixel step is biased for negative ones, measured
    # ~0.3 px): shift b's rectified principal point by whole pixels.
    shift = max(0, int(np.ceil(2.0 - d_min)))
    P2 = P2.copy()
    P2[ax, 2] += shift if flip else -shift
    offset += shift
    d_min += shift
    d_max += shift
    min_disp = int(np.floor(d_min))
    num = int(np.ceil((d_max - min_disp + 1) / 16.0) * 16)
    if num <= 0 or num > 16 * 16:  # a degenerate pair (or a huge range): no stereo
        return np.zeros((h, w), np.float32)
    if min_disp + num > span - params.block_size:  # OpenCV's SGBM crashes (segfault) on these
        return np.zeros((h, w), np.float32)
    maps_a = cv2.initUndistortRectifyMap(Ka, zero, R1, P1, size, cv2.CV_32FC1)
    maps_b = cv2.initUndistortRectifyMap(Kb, zero, R2, P2, size, cv2.CV_32FC1)
    left = cv2.remap(_gray(image_a), *maps_a, cv2.INTER_LINEAR)
    right = cv2.remap(_gray(image_b), *maps_b, cv2.INTER_LINEAR)
    m_left = cv2.remap(mask_a.astype(np.uint8), *maps_a, cv2.INTER_NEAREST) > 0
    m_right = cv2.remap(mask_b.astype(np.uint8), *maps_b, cv2.INTER_NEAREST) > 0
    if vertical:
        left, right, m_left, m_right = (x.T for x in (left, right, m_left, m_right))
    if flip:
        left, right = left[:, ::-1], right[:, ::-1]
        m_left, m_right = m_left[:, ::-1], m_right[:, ::-1]
    left, right = np.ascontiguousarray(left), np.ascontiguousarray(right)
    bs = params.block_size
    sgbm = cv2.StereoSGBM_create(
        minDisparity=min_disp,
        numDisparities=num,
        blockSize=bs,
        P1=8 * bs * bs,
        P2=32 * bs * bs,
        disp12MaxDiff=-1,
        uniquenessRatio=params.uniqueness_ratio,
        speckleWindowSize=params.speckle_window,
        speckleRange=params.speckle_range,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    disp_l = sgbm.compute(left, right).astype(np.float32) / 16.0  # [H, W] (transposed: [W, H])
    right_matcher = cv2.ximgproc.createRightMatcher(sgbm)
    disp_r = right_matcher.compute(right, left).astype(np.float32) / 16.0  # negative values
    valid = (disp_l > min_disp - 0.5) & (disp_l - offset > 0) & m_left
    rows, cols = np.nonzero(valid)
    xr = np.round(cols - disp_l[rows, cols]).astype(int)
    ok = (xr >= 0) & (xr < span)
    good = np.zeros_like(valid)
    r2, c2, x2 = rows[ok], cols[ok], xr[ok]
    consistent = np.abs(disp_l[r2, c2] + disp_r[r2, x2]) <= params.lr_max_diff
    consistent &= m_right[r2, x2]
    good[r2[consistent], c2[consistent]] = True
    disp = np.where(good, disp_l - offset, 0.0)  # f B / z
    if flip:
        disp = disp[:, ::-1]
    if vertical:
        disp = disp.T  # [H, W], the rectified image's own layout

    # back to view a's pixel grid: original pixel -> rectified pixel (pure rotation + new K).
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2)  # [HW, 2]
    pix = np.concatenate([grid, np.ones((len(grid), 1))], 1).astype(np.float64)  # OpenCV pixels
    ray = pix @ np.linalg.inv(Ka).T  # [HW, 3], z = 1 in camera a
    ray_rect = ray @ R1.T
    uv_rect = ray_rect @ P1[:, :3].T
    u = uv_rect[:, 0] / uv_rect[:, 2]
    v = uv_rect[:, 1] / uv_rect[:, 2]
    col = np.round(u).astype(int)
    row = np.round(v).astype(int)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h) & (uv_rect[:, 2] > 0)
    d = np.zeros(len(grid))
    d[inside] = disp[row[inside], col[inside]]
    # rectified z' = f B / d; along this ray camera-a z = z' / ray_rect_z (ray has z_a = 1).
    z = np.zeros(len(grid))
    pos = d > 0
    z[pos] = f_rect * baseline / d[pos] / ray_rect[pos, 2]
    z = z.reshape(h, w).astype(np.float32)
    z[~mask_a] = 0.0
    return z


def stereo_depth(
    cameras: list[Camera],
    images: list[np.ndarray],
    masks: list[np.ndarray],
    i: int,
    z_range: tuple[float, float],
    params: StereoParams | None = None,
    agree: float = 0.01,
) -> np.ndarray:
    """Depth [H, W] of view i from its (up to two) neighbours; where both answer they must agree
    within `agree` (run units) and are averaged; 0 = no answer."""
    params = params or StereoParams()
    maps = []
    for j in neighbours(cameras, i, params):
        try:
            maps.append(
                pair_depth(
                    cameras[i],
                    cameras[j],
                    images[i],
                    images[j],
                    masks[i],
                    masks[j],
                    z_range,
                    params,
                )
            )
        except cv2.error:  # rectification/SGBM failed on this pair: stereo has no answer there
            continue
    if not maps:
        return np.zeros(masks[i].shape, np.float32)
    if len(maps) == 1:
        return maps[0]
    a, b = maps[0], maps[1]
    both = (a > 0) & (b > 0)
    out = np.where(a > 0, a, b)
    out[both] = np.where(np.abs(a - b)[both] <= agree, 0.5 * (a + b)[both], 0.0)
    return out.astype(np.float32)
