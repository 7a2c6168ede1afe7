"""The "general object" shape prior of geometric editing (paper Sec. 3.2 (2), DESIGN.md section 7).

From the template's rendering of the edited view and the user's target we build the prior mesh M_P:

1. **2D correspondences** template view -> target: dense optical flow (OpenCV DIS) on the two
   images, and, for pixels on the template's silhouette, the flow's end point snapped to the
   nearest point of the target's silhouette (flow is weak where the object grows into a plain
   background; the contour is not).
2. **Lifting to 3D**: the proxy vertices visible in the edited view (projected depth agrees with
   the ray-cast depth of the proxy) and inside the editable region become handles. A handle
   moves along the one object axis (the scene's up axis, or the proxy's longer or shorter
   horizontal axis) whose image explains its 2D motion: a car seen from three quarters and made
   longer grows along its length, not across the view. A motion no axis explains (a drag along a
   diagonal) moves it to where the ray of its corresponded pixel crosses the upright plane
   through it (facing the camera, containing the up axis: an image-vertical drag lifts to a
   vertical move, as a photo of an upright object is read), or, without an up axis, at its
   camera depth.
   Vertices that project outside the region are anchored where they are (hidden ones too);
   hidden ones behind the region are free, so the far side of the edited part follows.
3. **ARAP**: Open3D `deform_as_rigid_as_possible` deforms the proxy so that handles reach their
   targets and anchors stay; the hidden side follows rigidly.
4. `symmetric=True`: the proxy's mirror plane (best of candidate planes through the centroid) is
   detected and every handle's displacement is mirrored onto the vertex opposite it (when that one
   is not itself constrained), so both sides of a symmetric object follow an edit seen on one side.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
from scipy import ndimage
from scipy.spatial import cKDTree

from render.cameras import Camera
from render.errors import SineError


@dataclass
class PriorMesh:
    """The ARAP prior M_P: the proxy's vertices moved (same triangles as the proxy)."""

    vertices: np.ndarray  # [V, 3] deformed proxy vertices (run units)
    triangles: np.ndarray  # [T, 3]
    displacement: np.ndarray  # [V] |M_P - proxy|
    handle_ids: np.ndarray  # [H] constrained vertices that move
    anchor_ids: np.ndarray  # [A] constrained vertices that stay
    mirror_plane: np.ndarray | None  # [4] (n, D) with n.x = D, when symmetric

    def moved(self, tol: float) -> np.ndarray:
        """[V] bool: vertices the prior moved by more than `tol`."""
        return self.displacement > tol


# ---- 2D correspondences -------------------------------------------------------------------
def _gray8(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Object over black as 8-bit grey (the silhouette becomes a strong edge for the flow)."""
    gray = cv2.cvtColor(np.clip(rgb, 0, 1).astype(np.float32), cv2.COLOR_RGB2GRAY)
    return np.clip(gray * alpha * 255.0, 0, 255).astype(np.uint8)


def dense_flow(
    template_rgb: np.ndarray,
    template_alpha: np.ndarray,
    target_rgb: np.ndarray,
    target_alpha: np.ndarray,
) -> np.ndarray:
    """Flow [H, W, 2] (dx, dy): template pixel p corresponds to target pixel p + flow(p)."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    a = _gray8(template_rgb, template_alpha)
    b = _gray8(target_rgb, target_alpha)
    return dis.calc(a, b, None)


def silhouette_boundary(alpha: np.ndarray) -> np.ndarray:
    """[H, W] bool: object pixels (alpha > 0.5) with a background 4-neighbour."""
    inside = alpha > 0.5
    return inside & ~ndimage.binary_erosion(inside, border_value=0)


def snap_to_contour(points: np.ndarray, target_alpha: np.ndarray, max_px: float) -> np.ndarray:
    """Pixel positions [N, 2] (u, v) -> the nearest target-silhouette boundary pixel centre,
    where one lies within `max_px`; others unchanged."""
    boundary = silhouette_boundary(target_alpha)
    if not boundary.any():
        return points
    dist, (rows, cols) = ndimage.distance_transform_edt(~boundary, return_indices=True)
    h, w = boundary.shape
    j = np.clip(points[:, 0].astype(int), 0, w - 1)
    i = np.clip(points[:, 1].astype(int), 0, h - 1)
    near = dist[i, j] <= max_px
    out = points.copy()
    out[near, 0] = cols[i[near], j[near]] + 0.5
    out[near, 1] = rows[i[near], j[near]] + 0.5
    return out


def bilinear(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Sample image [H, W, C] at pixel positions [N, 2] (u, v; centres at +0.5) -> [N, C]."""
    h, w = image.shape[:2]
    x = np.clip(points[:, 0] - 0.5, 0, w - 1)
    y = np.clip(points[:, 1] - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    img = image.reshape(h, w, -1)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


# ---- lifting to 3D ------------------------------------------------------------------------
def visible_vertices(
    camera: Camera, vertices: np.ndarray, depth: np.ndarray, tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vertices [V, 3] seen by `camera` given the proxy's camera-z map [H, W] (0 = no hit).

    -> (visible [V] bool, in the image [V] bool, pixel row [V], pixel col [V]).
    """
    row, col, in_image, z = camera.pixels_of(vertices, depth.shape)
    # the smallest depth around the vertex's pixel (a vertex on an edge touches several pixels)
    surface = ndimage.minimum_filter(np.where(depth > 0, depth, np.inf), size=3)
    d = surface[row, col]
    visible = in_image & np.isfinite(d) & (z <= d + tol)
    return visible, in_image, row, col


def lifting_normal(camera: Camera, up: np.ndarray | None) -> np.ndarray:
    """[3] normal of the planes handles move in: the camera's optical axis (the image plane: the
    vertex keeps its depth) or, with the scene's `up` [3], that axis made horizontal (the upright
    plane facing the camera), so image-vertical motion lifts to vertical motion. A camera looking
    more than 60 degrees down or up falls back to the image plane."""
    axis = camera.camera_to_world[:3, 2]
    normal = axis
    if up is not None:
        up = np.asarray(up, np.float64) / np.linalg.norm(up)
        level = axis - (axis @ up) * up
        if np.linalg.norm(level) > np.cos(np.radians(60.0)):
            normal = level / np.linalg.norm(level)
    return normal


def lift_to_planes(
    camera: Camera, pixels: np.ndarray, points: np.ndarray, normal: np.ndarray
) -> np.ndarray:
    """World points [N, 3] where the rays of `pixels` [N, 2] cross the planes through `points`
    [N, 3] with `normal` [3]."""
    directions = back_project(camera, pixels, np.ones(len(pixels))) - camera.center
    t = ((points - camera.center) @ normal) / (directions @ normal)
    return camera.center + t[:, None] * directions


def back_project(camera: Camera, pixels: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Pixel positions [N, 2] at camera depths z [N] -> world points [N, 3]."""
    x = (pixels[:, 0] - camera.cx) / camera.fx * z
    y = (pixels[:, 1] - camera.cy) / camera.fy * z
    cam = np.stack([x, y, z], axis=1)
    c2w = camera.camera_to_world
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def object_axes(vertices: np.ndarray, up: np.ndarray, min_ratio: float = 1.1) -> np.ndarray:
    """[K, 3] unit directions an edit most likely moves the object along: the scene's `up` [3],
    and the two principal axes of the shape [V, 3] in the horizontal plane when its horizontal
    spread is clearly longer one way (std ratio >= `min_ratio`; a round shape has no such axes)."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    flat = vertices - vertices.mean(axis=0)
    flat = flat - np.outer(flat @ up, up)
    _, spread, axes = np.linalg.svd(flat, full_matrices=False)  # the third axis is `up`
    if spread[1] <= 0 or spread[0] / spread[1] < min_ratio:
        return up[None]
    return np.stack([up, axes[0], axes[1]])


def lift_to_axes(
    camera: Camera,
    pixels: np.ndarray,
    points: np.ndarray,
    axes: np.ndarray,
    max_residual: float = 0.25,
) -> tuple[np.ndarray, np.ndarray]:
    """Moves each point [N, 3] along the one direction of `axes` [K, 3] whose image best explains
    its 2D motion to `pixels` [N, 2] (the point on the axis line nearest the pixel's ray).

    -> (moved points [N, 3], explained [N] bool: the best axis's reprojection error is within
    `max_residual` x the motion; the others are unusable, left in place)."""
    uv, _ = camera.project(points)
    motion = np.linalg.norm(pixels - uv, axis=1)  # [N]
    rays = back_project(camera, pixels, np.ones(len(pixels))) - camera.center  # [N, 3]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    best = np.full(len(points), np.inf)
    moved = points.copy()
    w = points - camera.center  # [N, 3]
    for axis in axes:
        # nearest points of the lines points + t axis and centre + s ray
        b = rays @ axis
        denom = 1.0 - b**2
        t = (b * (w * rays).sum(axis=1) - w @ axis) / np.maximum(denom, 1e-9)
        t[denom <= 1e-9] = 0.0  # the axis along the ray: no motion it can explain
        candidate = points + t[:, None] * axis
        err = np.linalg.norm(camera.project(candidate)[0] - pixels, axis=1)
        better = err < best
        best[better], moved[better] = err[better], candidate[better]
    return moved, best <= max_residual * np.maximum(motion, 1e-9)


@dataclass
class Handles:
    ids: np.ndarray  # [H] vertex ids that move
    targets: np.ndarray  # [H, 3] their positions in the edited shape
    anchor_ids: np.ndarray  # [A] vertex ids that stay


def lift_handles(
    camera: Camera,
    vertices: np.ndarray,
    proxy_depth: np.ndarray,
    flow: np.ndarray,
    region: np.ndarray,
    template_alpha: np.ndarray,
    target_alpha: np.ndarray,
    visibility_tol: float,
    contour_px: float = 3.0,
    min_motion_px: float = 1.0,
    up: np.ndarray | None = None,
    axes: np.ndarray | None = None,
) -> Handles:
    """Handles and anchors from the correspondences of view `camera` (see the module doc).

    Visible vertices inside `region` [H, W] bool whose corresponded pixel moved by more than
    `min_motion_px` follow it (handles): along the one of `axes` [K, 3] that explains the motion
    (`lift_to_axes`), else in the upright plane through them when the scene's `up` [3] is given,
    else at their camera depth (`lifting_normal`). Every other vertex whose
    projection falls outside the region is an anchor, hidden or not: the region's prism along the
    view is the only space the edit may change, and a hidden side left free would swing about the
    visible one. The rest (hidden behind the region, or visible in it with sub-pixel motion: flow
    noise) is free or anchored respectively.
    """
    visible, in_image, py, px = visible_vertices(camera, vertices, proxy_depth, visibility_tol)
    uv, _ = camera.project(vertices)  # [V, 2]
    in_region = in_image & region[py, px]
    ids = np.nonzero(visible & in_region)[0]
    src = uv[ids]
    dst = src + bilinear(flow, src)
    on_contour = ndimage.binary_dilation(
        silhouette_boundary(template_alpha), iterations=int(contour_px)
    )[py[ids], px[ids]]
    dst[on_contour] = snap_to_contour(dst[on_contour], target_alpha, 2 * contour_px)
    # a correspondence that lands outside the target's object is a flow error: drop it
    lands = bilinear(target_alpha[..., None].astype(np.float32), dst)[:, 0] > 0.25
    moves = np.linalg.norm(dst - src, axis=1) > min_motion_px
    still = ids[~moves]
    ids, dst = ids[lands & moves], dst[lands & moves]
    anchors = np.concatenate([np.nonzero(~in_region)[0], still])
    targets = lift_to_planes(camera, dst, vertices[ids], lifting_normal(camera, up))
    if axes is not None:
        along, explained = lift_to_axes(camera, dst, vertices[ids], axes)
        targets[explained] = along[explained]
    return Handles(ids, targets, np.unique(anchors))


# ---- symmetry -----------------------------------------------------------------------------
def reflect(points: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """Mirror points [N, 3] in the plane (n, D) with n.x = D, |n| = 1."""
    n, d = plane[:3], plane[3]
    return points - 2.0 * ((points @ n) - d)[:, None] * n


def mirror_plane(vertices: np.ndarray, max_error: float = 0.02) -> np.ndarray | None:
    """The best mirror plane (n, D) of a shape [V, 3] among planes through the centroid normal to
    its principal axes and to the horizontal axes x, y; None when the best one's mean
    reflection error exceeds `max_error` x the shape's radius."""
    centre = vertices.mean(axis=0)
    radius = float(np.linalg.norm(vertices - centre, axis=1).max())
    _, _, axes = np.linalg.svd(vertices - centre, full_matrices=False)
    candidates = list(axes) + [np.array([1.0, 0, 0]), np.array([0, 1.0, 0])]
    tree = cKDTree(vertices)
    best, best_err = None, np.inf
    for n in candidates:
        n = n / np.linalg.norm(n)
        plane = np.append(n, n @ centre)
        err = float(tree.query(reflect(vertices, plane))[0].mean())
        if err < best_err:
            best, best_err = plane, err
    return best if best_err <= max_error * radius else None


def proxy_mirror_plane(run) -> np.ndarray | None:
    """The mirror plane (n, D) of a run's proxy mesh (`mirror_plane`), or None."""
    import trimesh

    from recon.fit_proxy import template_proxy

    mesh = trimesh.load(template_proxy(run), force="mesh", process=False)
    return mirror_plane(np.asarray(mesh.vertices, np.float64))


def mirror_handles(handles: Handles, vertices: np.ndarray, plane: np.ndarray) -> Handles:
    """Adds, for every handle, the vertex opposite it moved by the mirrored displacement (unless
    that vertex is already a handle or an anchor, or lies on the plane itself)."""
    taken = set(handles.ids.tolist()) | set(handles.anchor_ids.tolist())
    _, opposite = cKDTree(vertices).query(reflect(vertices[handles.ids], plane))
    n = plane[:3]
    new_ids, new_targets = [], []
    for k, j in enumerate(opposite):
        if j in taken or j == handles.ids[k]:
            continue
        delta = handles.targets[k] - vertices[handles.ids[k]]
        mirrored = delta - 2.0 * (delta @ n) * n
        new_ids.append(j)
        new_targets.append(vertices[j] + mirrored)
        taken.add(j)
    if not new_ids:
        return handles
    return Handles(
        np.concatenate([handles.ids, new_ids]),
        np.concatenate([handles.targets, np.asarray(new_targets)]),
        handles.anchor_ids,
    )


# ---- ARAP ---------------------------------------------------------------------------------
def arap_deform(
    vertices: np.ndarray,
    triangles: np.ndarray,
    ids: np.ndarray,
    targets: np.ndarray,
    iterations: int = 50,
) -> np.ndarray:
    """Open3D ARAP: vertices [V, 3] with `ids` [K] constrained to `targets` [K, 3] -> [V, 3]."""
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
        o3d.utility.Vector3iVector(np.asarray(triangles, np.int32)),
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        out = mesh.deform_as_rigid_as_possible(
            o3d.utility.IntVector(np.asarray(ids, np.int32).tolist()),
            o3d.utility.Vector3dVector(np.asarray(targets, np.float64)),
            max_iter=iterations,
        )
    moved = np.asarray(out.vertices)
    if len(moved) != len(vertices) or not np.isfinite(moved).all():
        raise SineError(
            "the ARAP shape prior failed on the proxy mesh (non-manifold?); re-run `sine recon` "
            "or edit with --prior-weight 0"
        )
    return moved


def build_prior_mesh(
    camera: Camera,
    vertices: np.ndarray,
    triangles: np.ndarray,
    proxy_depth: np.ndarray,
    template_rgb: np.ndarray,
    template_alpha: np.ndarray,
    target_rgb: np.ndarray,
    target_alpha: np.ndarray,
    region: np.ndarray,
    visibility_tol: float = 0.02,
    symmetric: bool = False,
    iterations: int = 50,
    up: np.ndarray | None = None,
    axes: np.ndarray | None = None,
) -> PriorMesh:
    """The whole prior: correspondences -> handles -> (mirror) -> ARAP (see the module doc).
    `up` [3]: the scene's up axis for the upright lifting (None: handles keep their depth);
    `axes` [K, 3]: the object's axes a handle moves along when one explains it (`object_axes`;
    None: the planes only)."""
    flow = dense_flow(template_rgb, template_alpha, target_rgb, target_alpha)
    handles = lift_handles(
        camera,
        vertices,
        proxy_depth,
        flow,
        region,
        template_alpha,
        target_alpha,
        visibility_tol,
        up=up,
        axes=axes,
    )
    if len(handles.ids) == 0:
        raise SineError(
            "no proxy vertex is visible inside the editable region of the edited view; "
            "check --view (it must be the view the target was made from) and --region"
        )
    plane = mirror_plane(vertices) if symmetric else None
    if symmetric and plane is None:
        raise SineError("--symmetric: the proxy mesh has no clear mirror plane")
    if plane is not None:
        handles = mirror_handles(handles, vertices, plane)
    ids = np.concatenate([handles.ids, handles.anchor_ids])
    targets = np.concatenate([handles.targets, vertices[handles.anchor_ids]])
    moved = arap_deform(vertices, triangles, ids, targets, iterations)
    return PriorMesh(
        vertices=moved,
        triangles=np.asarray(triangles),
        displacement=np.linalg.norm(moved - vertices, axis=1),
        handle_ids=handles.ids,
        anchor_ids=handles.anchor_ids,
        mirror_plane=plane,
    )
