"""Turntable pose model: one rotation axis, one fixed camera, one angle per view.

A turntable capture (a fixed camera and a turning object, or a camera on a ring) has far fewer
unknowns than N free poses: the camera's pose relative to the axis (its orientation, 3 numbers;
its distance fixes the scale) and one angle per view. In the model's frame the axis is +z
through the origin, camera 0 sits at (1, 0, 0) and view i is camera 0 turned by theta_i about z:

    camera_to_world_i = Rz(theta_i) @ [R0 | (1, 0, 0)]

(the height of the camera along the axis and the world's scale and azimuth are gauge: the run's
normalisation follows). Intrinsics: the capture's when it has them, else those SfM estimated,
else the focal length of a 45 degree field of view (COLMAP's default prior, 1.2 x the longer
image side) refined with the rest.

Solving (`solve_turntable`):
1. Initial values. From the views an SfM model registered consistently (`seed_from_cameras`: the
   camera centres' circle gives the axis, each registered camera its angle and R0, their mean
   R0); the other views' angles follow from the turning step in capture order. Without a seed:
   angles evenly around 360 degrees (or `step_deg` apart), both turning directions, camera
   elevations of -10..50 degrees and image rolls of 0/90/180/270 degrees (image up = axis or
   not), the candidate whose silhouettes agree best wins.
2. Silhouette coherence (`coherence`): every view's contour pixels cast rays; a ray must pass
   through the visual hull of the other views, i.e. through a point inside every other
   silhouette. Per ray, e = max over depth of min over the other views of the signed distance
   (pixels, positive inside) of the point's projection to their mask outline; a ray that misses
   the hull has e < 0. The loss is the mean of min(e, 0)^2 (pixels^2), minimised over the
   angles, R0 (and the focal length when unknown) with Adam, coarse depth samples finding the
   best depth and fine ones around it carrying the gradient.

The silhouettes of a body of revolution do not change as it turns: its angles then stay where
they started (even steps), which `angles_observable` reports.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from render.cameras import Camera, look_at
from render.errors import SineError

DEFAULT_FOCAL_FACTOR = 1.2  # focal length / longer image side without calibration (COLMAP)
SEARCH_VIEWS = 16  # views the search for starting values looks at
SEARCH_ELEVATIONS = (-10.0, 0.0, 10.0, 20.0, 30.0, 40.0, 50.0)  # degrees
SEARCH_ROLLS = (0.0, 90.0, 180.0, 270.0)  # degrees
SEARCH_STEP_FACTORS = (0.88, 0.91, 0.94, 0.97, 1.0, 1.03, 1.06, 1.09, 1.12)  # x 360 / views
SEARCH_KEEP = 3  # candidates of the search refined briefly before the best goes on
SEED_GOOD_LOSS = 0.5  # pixels: an SfM seed this coherent needs no search


@dataclass
class TurntableParams:
    """Knobs of the turntable solver (filled from ReconConfig)."""

    step_deg: float | None = None  # turn between consecutive views; None = 360 / views
    contour_samples: int = 64  # contour pixels per view
    depth_samples: int = 64  # coarse samples along each contour ray
    fine_samples: int = 9  # samples around the best coarse depth (carry the gradient)
    iterations: int = 300
    search_iterations: int = 40  # short refinement of each initial candidate
    lr_deg: float = 0.5  # Adam step for angles and R0 (degrees)
    max_width: int = 400  # masks are scaled down to at most this width
    max_other_views: int = 12  # each contour ray is tested in this many other views
    sdf_clip: float = 1000.0  # pixels


@dataclass
class TurntableResult:
    cameras: list[Camera]  # every view, capture order, at the masks' size
    angles_deg: np.ndarray  # [N] theta_i (view 0 = 0)
    elevation_deg: float  # angle of camera 0's optical axis below the plane of the ring
    loss_px: float  # final coherence loss
    init: str  # where the initial values came from
    focal_refined: bool
    angles_observable: bool


# ---- geometry -----------------------------------------------------------------------------
def rotvec_to_matrix(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: rotation vector [3] -> rotation [3, 3] (differentiable, also at 0)."""
    theta2 = (w * w).sum()
    theta = torch.sqrt(theta2 + 1e-24)
    k = torch.zeros(3, 3, dtype=w.dtype)
    k[0, 1], k[0, 2], k[1, 0] = -w[2], w[1], w[2]
    k[1, 2], k[2, 0], k[2, 1] = -w[0], -w[1], w[0]
    small = theta2 < 1e-12
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / (theta2 + 1e-24))
    return torch.eye(3, dtype=w.dtype) + a * k + b * (k @ k)


def ring_poses(r0: torch.Tensor, angles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-to-world rotations [N, 3, 3] and centres [N, 3] of the turntable model."""
    c, s = torch.cos(angles), torch.sin(angles)
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    rz = torch.stack(
        [
            torch.stack([c, -s, zero], -1),
            torch.stack([s, c, zero], -1),
            torch.stack([zero, zero, one], -1),
        ],
        -2,
    )  # [N, 3, 3]
    rot = rz @ r0
    centres = rz[:, :, 0]  # Rz @ (1, 0, 0)
    return rot, centres


def initial_r0(elevation_deg: float, roll_deg: float) -> np.ndarray:
    """Camera 0 at (1, 0, 0) looking at the axis from `elevation_deg` above, image turned by
    `roll_deg` about its optical axis (0 = image up along +z)."""
    e = np.radians(elevation_deg)
    c2w = look_at(np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, -np.tan(e)]))
    r = np.radians(roll_deg)
    roll = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1.0]])
    return c2w[:3, :3] @ roll


def elevation_of(r0: np.ndarray) -> float:
    """Degrees the optical axis of camera 0 points below the ring's plane."""
    return float(np.degrees(np.arcsin(np.clip(-r0[2, 2], -1, 1))))


# ---- silhouettes --------------------------------------------------------------------------
@dataclass
class Silhouettes:
    sdf: torch.Tensor  # [N, 1, H, W] signed distance to the outline, pixels, + inside
    contour: torch.Tensor  # [N, C, 2] contour pixel centres (u, v) of each view
    width: int
    height: int
    scale: float  # mask pixels per working pixel


def prepare_silhouettes(
    masks: list[np.ndarray], contour_samples: int, max_width: int, clip: float
) -> Silhouettes:
    """Signed distance maps and evenly spaced contour samples of each mask (holes filled: a
    dark patch keyed out of an object must not carve the hull)."""
    h0, w0 = masks[0].shape
    s = min(1.0, max_width / w0)
    w, h = max(8, round(w0 * s)), max(8, round(h0 * s))
    sdfs, contours = [], []
    for m in masks:
        m = cv2.resize(m.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) >= 0.5
        if not m.any():
            raise SineError("a mask is empty: the turntable model needs the object in every view")
        found, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        m8 = cv2.drawContours(np.zeros((h, w), np.uint8), found, -1, 1, cv2.FILLED)  # no holes
        inside = cv2.distanceTransform(m8, cv2.DIST_L2, 5)
        outside = cv2.distanceTransform(1 - m8, cv2.DIST_L2, 5)
        sdfs.append(np.clip(np.where(m8 > 0, inside - 0.5, 0.5 - outside), -clip, clip))
        pts = np.concatenate([c.reshape(-1, 2) for c in found]).astype(np.float64)  # (x, y)
        idx = np.linspace(0, len(pts), contour_samples, endpoint=False).astype(int)
        contours.append(pts[idx] + 0.5)  # pixel centres
    sdf = torch.tensor(np.stack(sdfs)[:, None], dtype=torch.float32)
    contour = torch.tensor(np.stack(contours), dtype=torch.float64)
    return Silhouettes(sdf, contour, w, h, s)


# ---- coherence ----------------------------------------------------------------------------
class Coherence:
    """Silhouette coherence of turntable cameras (module doc, step 2).

    Depths along a contour ray are sampled where it passes the axis: within the radius the
    object can have around it (1.3 x the widest angle between a mask pixel and the optical
    axis, at the optical axis' distance to the axis) of the ray's closest approach to it.
    """

    def __init__(self, sil: Silhouettes, params: TurntableParams, k: tuple):
        self.sil, self.p = sil, params
        fx, fy, cx, cy = k
        pix = sil.contour
        tan = torch.sqrt(((pix[..., 0] - cx) / fx) ** 2 + ((pix[..., 1] - cy) / fy) ** 2)
        self.object_tan = 1.3 * float(tan.max())
        self.unit = torch.linspace(-1, 1, params.depth_samples, dtype=torch.float64)
        n = sil.sdf.shape[0]
        count = min(n - 1, params.max_other_views)
        self.offsets = sorted({int(round(x)) for x in np.linspace(1, n - 1, count)})

    def subset(self, stride: int, contour_stride: int = 1, depth_samples: int = 0) -> Coherence:
        """The same coherence on every `stride`-th view (every `contour_stride`-th contour
        sample, `depth_samples` coarse depths or the same)."""
        sil = self.sil
        contour = sil.contour[::stride, ::contour_stride]
        sub = Silhouettes(sil.sdf[::stride], contour, sil.width, sil.height, sil.scale)
        out = Coherence.__new__(Coherence)
        out.sil, out.p, out.object_tan = sub, self.p, self.object_tan
        m = depth_samples or len(self.unit)
        out.unit = torch.linspace(-1, 1, m, dtype=torch.float64)
        n = sub.sdf.shape[0]
        count = min(n - 1, self.p.max_other_views)
        out.offsets = sorted({int(round(x)) for x in np.linspace(1, n - 1, count)})
        return out

    def _sample(self, rot, centres, k, points: torch.Tensor) -> torch.Tensor:
        """min over the other views of the signed distance at points [N, C, M, 3] -> [N, C, M]
        (view k's points seen by views k + offset, for up to `max_other_views` offsets)."""
        n, c, m, _ = points.shape
        fx, fy, cx, cy = k
        flat = points.reshape(n, -1, 3).float()  # float32: half the memory traffic
        rot, centres = rot.float(), centres.float()
        out = None
        for offset in self.offsets:
            j = (torch.arange(n) + offset) % n
            local = (flat - centres[j][:, None, :]) @ rot[j]  # [N, P, 3] (R^T (X - c))
            z = local[..., 2]
            u = fx * local[..., 0] / z.clamp_min(1e-6) + cx
            v = fy * local[..., 1] / z.clamp_min(1e-6) + cy
            gx = 2 * u / self.sil.width - 1
            gy = 2 * v / self.sil.height - 1
            grid = torch.stack([gx, gy], -1).to(torch.float32)[:, :, None, :]  # [N, P, 1, 2]
            val = torch.nn.functional.grid_sample(
                self.sil.sdf[j], grid, mode="bilinear", padding_mode="border", align_corners=False
            )[:, 0, :, 0]  # [N, P]
            seen = (z > 1e-6) & (gx.abs() <= 1) & (gy.abs() <= 1)
            val = torch.where(seen, val, torch.full_like(val, 1e3))  # unseen: no constraint
            out = val if out is None else torch.minimum(out, val)
        return out.reshape(n, c, m)

    def _directions(self, rot, k) -> torch.Tensor:
        """World directions [N, C, 3] of the contour rays."""
        fx, fy, cx, cy = k
        pix = self.sil.contour
        d = torch.stack(
            [(pix[..., 0] - cx) / fx, (pix[..., 1] - cy) / fy, torch.ones_like(pix[..., 0])], -1
        )
        d = d @ rot.transpose(1, 2)  # R d
        return d / d.norm(dim=-1, keepdim=True)

    def _window(self, rot, centres, d) -> tuple[torch.Tensor, torch.Tensor]:
        """Centre [N, C] and half-width [N, C] of the depths sampled along each ray."""
        oxy, dxy = centres[:, None, :2], d[..., :2]
        dxy2 = (dxy * dxy).sum(-1).clamp_min(1e-4)
        t_star = (-(oxy * dxy).sum(-1) / dxy2).clamp_min(1e-3)
        axis = rot[:, :, 2]  # optical axes [N, 3]
        a2 = (axis[:, :2] ** 2).sum(-1).clamp_min(1e-4)
        t_axis = (-(centres[:, :2] * axis[:, :2]).sum(-1) / a2).clamp_min(1e-3)  # [N]
        radius = self.object_tan * t_axis[:, None]
        half = torch.minimum(radius / dxy2.sqrt(), 3 * radius)
        return t_star, half

    def coarse_scores(self, rot, centres, k) -> tuple[torch.Tensor, torch.Tensor]:
        """(e [N, C] at the coarse depths, the best depth [N, C] and the sample spacing [N, C]
        as one tensor [2, N, C]), no gradient."""
        with torch.no_grad():
            d = self._directions(rot, k)
            centre, half = self._window(rot, centres, d)
            t = centre[..., None] + half[..., None] * self.unit  # [N, C, M]
            pts = centres[:, None, None, :] + t[..., None] * d[:, :, None, :]
            val = self._sample(rot, centres, k, pts)
            best, index = val.max(-1)
            t_best = torch.gather(t, -1, index[..., None])[..., 0]
            spacing = 2 * half / (len(self.unit) - 1)
        return best, torch.stack([t_best, spacing])

    def ray_scores(self, rot, centres, k, depths: torch.Tensor) -> torch.Tensor:
        """e [N, C]: how deep (pixels) each contour ray passes inside the others' hull, from
        fine depth samples around the coarse best `depths` (see coarse_scores; differentiable)."""
        d = self._directions(rot, k)
        offsets = torch.linspace(-1, 1, self.p.fine_samples, dtype=d.dtype)
        t = depths[0][..., None] + depths[1][..., None] * offsets  # [N, C, F]
        pts = centres[:, None, None, :] + t[..., None] * d[:, :, None, :]
        return self._sample(rot, centres, k, pts).max(-1).values

    @staticmethod
    def loss_of(e: torch.Tensor, scale: float = 2.0) -> torch.Tensor:
        """Mean over the rays of the robust (Charbonnier) size of their miss, min(e, 0), in
        pixels: quadratic within `scale`, linear beyond (a bad mask does not dominate, a far
        miss still pulls)."""
        miss = torch.clamp(e, max=0.0) / scale
        return (scale * (torch.sqrt(1 + miss * miss) - 1)).mean()

    def loss(self, rot, centres, k) -> torch.Tensor:
        """The coherence loss with fresh coarse depths (no gradient through their choice)."""
        _, depths = self.coarse_scores(rot, centres, k)
        return self.loss_of(self.ray_scores(rot, centres, k, depths))


# ---- initial values -----------------------------------------------------------------------
def seed_from_cameras(cameras: list[Camera], index: list[int], n: int, step_deg: float | None):
    """Turntable values from registered cameras (`index` = their capture positions among the
    n views): (R0 [3, 3], angles [n] radians) with the other views' angles from the step."""
    from recon.selfcheck import ring_fit

    ring = ring_fit(cameras)
    axis, centre, radius = ring["axis"], ring["centre"], ring["radius"]
    # the model frame: axis -> z, first registered camera's centre -> +x, radius -> 1
    x = cameras[0].center - centre
    x = x - (x @ axis) * axis
    x /= np.linalg.norm(x)
    basis = np.stack([x, np.cross(axis, x), axis])  # rows
    angles, r0s = [], []
    for cam in cameras:
        p = basis @ (cam.center - centre)
        a = np.arctan2(p[1], p[0])
        angles.append(a)
        rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        r0s.append(rz.T @ basis @ cam.camera_to_world[:3, :3])
    u, _, vt = np.linalg.svd(np.mean(r0s, axis=0))
    r0 = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
    angles = np.unwrap(np.array(angles))
    index = np.asarray(index)
    if len(index) >= 2:
        step = np.polyfit(index, angles, 1)[0]
    else:
        step = np.radians(step_deg or 360.0 / n)
    if step_deg is not None:
        step = np.sign(step) * np.radians(step_deg)
    full = np.empty(n)
    for i in range(n):
        j = int(np.argmin(np.abs(index - i)))
        full[i] = angles[j] + step * (i - index[j])
    full -= full[0]
    # radius and height of the ring are gauge; centres in the model frame must match R0's.
    _ = radius
    return r0, full


def even_angles(n: int, step_deg: float | None, direction: float) -> np.ndarray:
    step = np.radians(step_deg if step_deg is not None else 360.0 / n)
    return direction * step * np.arange(n)


# ---- solving ------------------------------------------------------------------------------
def _intrinsics(cam_or_none: Camera | None, w: int, h: int) -> tuple[tuple, bool]:
    """(fx, fy, cx, cy) at (w, h) and whether they are known."""
    if cam_or_none is not None:
        c = cam_or_none.resized(w, h)
        return (c.fx, c.fy, c.cx, c.cy), True
    f = DEFAULT_FOCAL_FACTOR * max(w, h)
    return (f, f, w / 2.0, h / 2.0), False


class _State(torch.nn.Module):
    def __init__(self, r0: np.ndarray, angles: np.ndarray, k: tuple, refine_focal: bool):
        super().__init__()
        self.r0 = torch.tensor(r0, dtype=torch.float64)
        self.w = torch.nn.Parameter(torch.zeros(3, dtype=torch.float64))
        self.angles = torch.nn.Parameter(torch.tensor(angles[1:], dtype=torch.float64))
        self.log_f = torch.nn.Parameter(torch.zeros(1, dtype=torch.float64))
        self.log_f.requires_grad_(refine_focal)
        self.k0 = k

    def poses(self):
        r0 = rotvec_to_matrix(self.w) @ self.r0
        angles = torch.cat([torch.zeros(1, dtype=torch.float64), self.angles])
        rot, centres = ring_poses(r0, angles)
        f = torch.exp(self.log_f[0])
        fx, fy, cx, cy = self.k0
        return rot, centres, (fx * f, fy * f, cx, cy)

    def values(self) -> tuple[np.ndarray, np.ndarray, tuple]:
        with torch.no_grad():
            r0 = (rotvec_to_matrix(self.w) @ self.r0).numpy()
            angles = np.concatenate([[0.0], self.angles.numpy()])
            f = float(torch.exp(self.log_f[0]))
        fx, fy, cx, cy = self.k0
        return r0, angles, (fx * f, fy * f, cx, cy)


def _refine(
    coh: Coherence, state: _State, iterations: int, lr_deg: float, every: int = 10
) -> float:
    """Adam on the state; the coarse best depths are refreshed every `every` steps."""
    lr = np.radians(lr_deg)
    groups = [{"params": [state.w, state.angles], "lr": lr}]
    if state.log_f.requires_grad:
        groups.append({"params": [state.log_f], "lr": lr})
    opt = torch.optim.Adam(groups)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(1, iterations), eta_min=lr * 0.05)
    depths = None
    for i in range(iterations):
        rot, centres, k = state.poses()
        if i % every == 0:
            _, depths = coh.coarse_scores(rot, centres, k)
        opt.zero_grad()
        loss = coh.loss_of(coh.ray_scores(rot, centres, k, depths))
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        return float(coh.loss(*state.poses()))


def search_start(coh: Coherence, n: int, params: TurntableParams, k: tuple) -> list[tuple]:
    """Even-step starting values, best first: (coarse loss, label, R0, angles [n]) for every
    turning direction, step (360 / n or `step_deg`, times SEARCH_STEP_FACTORS unless given),
    camera elevation and image roll of the grid, judged on every `stride`-th view with half
    the contour and depth samples (fast)."""
    stride = int(np.ceil(n / SEARCH_VIEWS))
    sub = coh.subset(stride, contour_stride=2, depth_samples=max(8, params.depth_samples // 2))
    base = params.step_deg if params.step_deg is not None else 360.0 / n
    factors = (1.0,) if params.step_deg is not None else SEARCH_STEP_FACTORS
    scored = []
    for direction in (1.0, -1.0):
        for factor in factors:
            angles = even_angles(n, base * factor, direction)
            for elevation in SEARCH_ELEVATIONS:
                for roll in SEARCH_ROLLS:
                    r0 = initial_r0(elevation, roll)
                    e, _ = sub.coarse_scores(*_State(r0, angles[::stride], k, False).poses())
                    label = (
                        f"even steps of {base * factor * direction:+.2f} deg, elevation "
                        f"{elevation:g}, roll {roll:g}"
                    )
                    scored.append((float(sub.loss_of(e)), label, r0, angles))
    return sorted(scored, key=lambda x: x[0])


def solve_turntable(
    masks: list[np.ndarray],
    params: TurntableParams,
    intrinsics: Camera | None = None,
    seed: tuple[list[Camera], list[int]] | None = None,
    names: list[str] | None = None,
    log=print,
) -> TurntableResult:
    """Turntable cameras for `masks` (capture order) by silhouette coherence (module doc).

    `intrinsics`: a camera whose intrinsics are known (any size with the masks' aspect);
    `seed`: registered cameras (consistent SfM) and their capture positions.
    """
    n = len(masks)
    if n < 3:
        raise SineError(f"the turntable model needs at least 3 views, got {n}")
    sil = prepare_silhouettes(masks, params.contour_samples, params.max_width, params.sdf_clip)
    k, known = _intrinsics(intrinsics, sil.width, sil.height)
    coh = Coherence(sil, params, k)

    candidates = []  # (label, r0, angles)
    best = None
    if seed is not None and len(seed[0]) >= 3:
        r0, angles = seed_from_cameras(seed[0], seed[1], n, params.step_deg)
        state = _State(r0, angles, k, not known)
        loss = _refine(coh, state, params.search_iterations, params.lr_deg)
        label = f"sfm seed ({len(seed[0])} views)"
        log(f"[recon] turntable: start from {label}: loss {loss:.3f} px")
        best = (loss, label, state)
    if best is None or best[0] > SEED_GOOD_LOSS:
        for loss, label, r0, angles in search_start(coh, n, params, k)[:SEARCH_KEEP]:
            log(f"[recon] turntable: candidate {label}: coarse loss {loss:.2f} px")
            candidates.append((label, r0, angles))
    for label, r0, angles in candidates:
        state = _State(r0, angles, k, not known)
        loss = _refine(coh, state, params.search_iterations, params.lr_deg)
        log(f"[recon] turntable: start from {label}: loss {loss:.3f} px")
        if best is None or loss < best[0]:
            best = (loss, label, state)
    _, label, state = best
    loss = _refine(coh, state, params.iterations, params.lr_deg)
    r0, angles, (fx, fy, cx, cy) = state.values()
    observable = angles_observable(coh, state)
    h0, w0 = masks[0].shape
    s = 1.0 / sil.scale
    cams = []
    for i, a in enumerate(angles):
        rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        c2w = np.eye(4)
        c2w[:3, :3] = rz @ r0
        c2w[:3, 3] = rz[:, 0]
        cam = Camera(sil.width, sil.height, fx, fy, cx, cy, c2w, name=names[i] if names else "")
        cams.append(cam.resized(w0, h0) if s != 1.0 else cam)
    return TurntableResult(
        cameras=cams,
        angles_deg=np.degrees(angles),
        elevation_deg=elevation_of(r0),
        loss_px=loss,
        init=label,
        focal_refined=not known,
        angles_observable=observable,
    )


def angles_observable(coh: Coherence, state: _State, turn_deg: float = 5.0) -> bool:
    """Whether the silhouettes pin the angles: turning every other view by `turn_deg` must
    raise the coherence loss noticeably (measured: x13 for a 96 px toy car, x66 at 160 px; a
    body of revolution: unchanged)."""
    with torch.no_grad():
        rot, centres, k = state.poses()
        base = float(coh.loss(rot, centres, k))
        angles = state.angles.detach().clone()
        shift = torch.zeros_like(angles)
        shift[::2] = np.radians(turn_deg)
        r0 = rotvec_to_matrix(state.w) @ state.r0
        rot2, centres2 = ring_poses(
            r0, torch.cat([torch.zeros(1, dtype=angles.dtype), angles + shift])
        )
        moved = float(coh.loss(rot2, centres2, k))
    return moved > 1.5 * base + 0.005


# ---- around the solver --------------------------------------------------------------------
def choose_seed(models: list, names: list[str], masks: list[np.ndarray], thresholds):
    """The SfM model with the most views (>= 3) whose views are consistent on their own: their
    visual hull explains their masks, their centres lie on one circle, monotone in capture
    order. Returns (its cameras, their capture positions) or None."""
    from recon.selfcheck import ring_fit, silhouette_consistency

    best = None
    for _, cams in models:
        if len(cams) < 3 or (best is not None and len(cams) <= len(best[0])):
            continue
        index = [names.index(c.name) for c in cams]
        ious = silhouette_consistency(cams, [masks[i] for i in index])
        ring = ring_fit(cams)
        if (
            ious.mean() >= thresholds.min_silhouette_iou
            and ring["ring_residual"] <= thresholds.max_ring_residual
            and ring["backward_deg"] <= thresholds.max_backward_deg
        ):
            best = (cams, index)
    return best


def rim_depth_ratios(
    cameras: list[Camera], masks: list[np.ndarray], depths: list[np.ndarray]
) -> dict[str, np.ndarray]:
    """Per view name: the ratios [M] of the visual hull's depth to the capture's depth on the
    rim of the mask (2 pixels wide), where the hull touches the object. Masks [H, W] and depths
    at the masks' size."""
    from recon.depth import raycast_views, visual_hull_mesh

    verts, faces, _ = visual_hull_mesh(cameras, masks, resolution=96)
    ratios = {}
    kernel = np.ones((5, 5), np.uint8)
    for cam, mask, hull, depth in zip(
        cameras, masks, raycast_views(verts, faces, cameras), depths, strict=True
    ):
        rim = mask & ~(cv2.erode(mask.astype(np.uint8), kernel) > 0)
        ok = rim & (hull > 0) & (depth > 0) & np.isfinite(depth)
        ratios[cam.name] = hull[ok] / depth[ok]
    return ratios


def partner_views(cameras: list[Camera], i: int, count: int = 2) -> list[int]:
    """Up to `count` views whose optical axes are 15-60 degrees from view i's, those nearest
    30 degrees first: wide enough to fix depth along view i's rays, close enough to see most
    of what view i sees."""
    axes = np.array([c.camera_to_world[:3, 2] for c in cameras])  # [N, 3]
    angles = np.degrees(np.arccos(np.clip(axes @ axes[i], -1.0, 1.0)))  # [N]
    order = np.argsort(np.abs(angles - 30.0))
    return [int(j) for j in order if 15.0 <= angles[j] <= 60.0][:count]


def bilinear_depth(depth: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Depth [H, W] (0 = none) read at pixel coordinates u, v (any shape, pixel centres at
    +0.5) by bilinear interpolation; NaN where any of the four neighbours has no depth or
    lies outside the image."""
    h, w = depth.shape
    x, y = u - 0.5, v - 0.5
    c, r = np.floor(x).astype(int), np.floor(y).astype(int)
    inside = (c >= 0) & (r >= 0) & (c < w - 1) & (r < h - 1)
    c, r = np.clip(c, 0, w - 2), np.clip(r, 0, h - 2)
    fx, fy = x - c, y - r
    d00, d01, d10, d11 = depth[r, c], depth[r, c + 1], depth[r + 1, c], depth[r + 1, c + 1]
    value = (1 - fy) * ((1 - fx) * d00 + fx * d01) + fy * ((1 - fx) * d10 + fx * d11)
    ok = inside & (d00 > 0) & (d01 > 0) & (d10 > 0) & (d11 > 0)
    return np.where(ok, value, np.nan)


def smooth_depth_pixels(depth: np.ndarray, mask: np.ndarray, jump: float = 0.02) -> np.ndarray:
    """Pixels [H, W] bool inside the mask (eroded by 2) whose 3 x 3 neighbourhood spans less
    than `jump` of their depth: away from outlines and occlusion edges."""
    kernel = np.ones((3, 3), np.uint8)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    has = depth > 0
    high = cv2.dilate(depth.astype(np.float32), kernel)
    low = cv2.erode(np.where(has, depth, np.inf).astype(np.float32), kernel)
    return inner & has & (high - low < jump * depth)


def consistent_depth_ratios(
    cameras: list[Camera],
    masks: list[np.ndarray],
    depths: list[np.ndarray],
    guess: float,
    points: int = 2000,
    span: float = 0.3,
    steps: int = 61,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """Per view name: ratios [M] (pose camera z / dataset depth) at which the view's pixels,
    lifted along their rays by ratio x their dataset depth, land on the dataset depth of a
    partner view (`partner_views`).

    For a pixel of view i with dataset depth D and ray p (z = 1 in camera i), the point at ratio
    k is X(k) = C_i + k D R_i p; in camera j it has depth z_j(k) and should meet view j's depth,
    scaled alike: z_j(k) = k D_j(proj_j X(k)). The relative residual is scanned over `steps`
    ratios spanning exp(+-span) around `guess`; a ratio is kept where it changes sign between
    two neighbouring ratios with small residuals on both sides (a continuous surface, not an
    occlusion edge), refined linearly, the crossing nearest `guess` when there are several.
    Unlike the visual hull's rim (`rim_depth_ratios`, biased by the hull's voxels), this uses
    the whole surface and every pair of overlapping views. Masks [H, W] and depths at the
    masks' size; cameras at any size."""
    rng = np.random.default_rng(seed)
    ratios = np.exp(np.linspace(-span, span, steps)) * guess  # [S]
    log_step = 2 * span / (steps - 1)
    cams = [c.resized(m.shape[1], m.shape[0]) for c, m in zip(cameras, masks, strict=True)]
    masked = [np.where(m, d, 0.0) for m, d in zip(masks, depths, strict=True)]
    out = {}
    for i, cam in enumerate(cams):
        rows, cols = np.nonzero(smooth_depth_pixels(depths[i], masks[i]))
        pick = rng.choice(len(rows), min(points, len(rows)), replace=False)
        rows, cols = rows[pick], cols[pick]
        lifted = np.linalg.inv(cam.K) @ np.stack([cols + 0.5, rows + 0.5, np.ones(len(rows))])
        lifted = cam.camera_to_world[:3, :3] @ (lifted * depths[i][rows, cols])  # [3, M] world
        found = []
        for j in partner_views(cams, i):
            other = cams[j]
            to_cam = other.camera_to_world[:3, :3].T
            offset = to_cam @ (cam.center - other.center)  # [3]
            along = to_cam @ lifted  # [3, M]
            local = offset[:, None, None] + along[:, :, None] * ratios  # [3, M, S]
            pix = np.einsum("ab,bms->ams", other.K, local)
            z = local[2]
            seen = bilinear_depth(masked[j], pix[0] / pix[2], pix[1] / pix[2])  # [M, S]
            res = np.where(z > 0, (z - ratios * seen) / (ratios * seen), np.nan)  # [M, S]
            a, b = res[:, :-1], res[:, 1:]
            cross = (a * b <= 0) & (np.abs(a) < 2 * log_step) & (np.abs(b) < 2 * log_step)
            frac = np.clip(a / np.where(a != b, a - b, 1.0), 0.0, 1.0)
            roots = np.where(cross, ratios[:-1] * np.exp(frac * log_step), np.nan)  # [M, S-1]
            dist = np.where(cross, np.abs(np.log(roots / guess)), np.inf)
            best = roots[np.arange(len(roots)), np.argmin(dist, axis=1)]
            found.append(best[np.isfinite(best)])
        out[cam.name] = np.concatenate(found) if found else np.zeros(0)
    return out
