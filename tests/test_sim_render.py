"""The simulated cube's images: tag corners land where the true cameras project them."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dataset_tools.calibration.tag_edges import refine_tag_corners
from dataset_tools.calibration.tag_intrinsics import MIN_FACE_ON
from rig.layouts import make_rig
from rig.sim import shapes
from rig.sim.cube import true_cameras
from rig.sim.render import LABEL_WALLS, Renderer
from rig.sim.world import World


def detector() -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)


def visible(world: World, centre: np.ndarray, corners: np.ndarray) -> bool:
    """False when the table stands between the camera and any corner of the tag."""
    d = corners - centre
    t, _ = shapes.ray_box(np.broadcast_to(centre, d.shape), d, world.table_lo, world.table_hi)
    return bool(np.all(t > 1.0 - 1e-9))


def corner_errors(resolution, cameras, min_side_px, world=None, tags=None):
    """Distances (px) of the refined corners of the tags `cameras` see (ids in `tags`, all by
    default) from their true projections; tags seen smaller than min_side_px, at a slant (the
    calibration leaves both out) or behind the table are not scored."""
    rig = make_rig("cube53", resolution=resolution, seed=1)
    cams = true_cameras(rig)
    world = world or World()
    renderer = Renderer(world, cams, supersample=2)
    det = detector()
    errors, n_tags = [], 0
    picks = [cams.index(c) for c in cameras] if isinstance(cameras, tuple) else \
        np.linspace(0, len(cams) - 1, cameras).round().astype(int)
    for i in picks:
        image = (renderer.render(int(i)).image * 255).round().astype(np.uint8)
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _ = det.detectMarkers(gray)
        one = cams.subset([cams.ids[i]])
        if ids is not None:
            corners = refine_tag_corners(gray, np.array(corners), one.K[0], one.dist[0])[:, None]
        for found, tag_id in zip(corners, ids.ravel() if ids is not None else []):
            truth = world.tags[int(tag_id)]
            projected = one.project(truth)[0]
            side = np.linalg.norm(projected - np.roll(projected, 1, axis=0), axis=1).min()
            normal = np.cross(truth[1] - truth[0], truth[3] - truth[0])
            view = truth.mean(axis=0) - cams.centers[i]
            slant = abs(normal @ view) / np.linalg.norm(normal) / np.linalg.norm(view) < MIN_FACE_ON
            if (tags is not None and int(tag_id) not in tags) or side < min_side_px or slant or \
                    not visible(world, cams.centers[i], truth):
                continue
            n_tags += 1
            errors.append(np.linalg.norm(found[0] - projected, axis=1))
    return np.concatenate(errors), n_tags


@pytest.mark.parametrize("resolution, cameras", [((320, 180), 14), ((1280, 720), 3)])
def test_tag_corners_within_half_a_pixel(resolution, cameras):
    # Every corner within 0.5 px (the bound); the median bound is what an exact renderer
    # and the edge refinement give together (measured 0.008 px at 320x180, 0.005 px at 1280x720
    # with the optics of issue 19; at most 0.27 px, a corner 3 px from the image's edge).
    errors, n_tags = corner_errors(resolution, cameras, min_side_px=12)
    assert n_tags >= 3 * cameras  # every camera sees several whole tags
    assert errors.max() < 0.5, np.percentile(errors, [50, 95, 100])
    assert np.median(errors) < 0.05


def test_tags_on_the_table_sides_land_where_they_are_projected():
    """The table's sides carry tags (World(table_tags=True)) for the cameras beside it, which see
    little else: their corners are as exact as the walls' (measured on the four floor cameras at
    640x360: 10 tags scored, median 0.011 px, max 0.037 px)."""
    world = World(tags_per_wall=8, tag_size=0.09, table_tags=True)
    table = {t for t, f in world.tag_faces().items() if f >= len(world.faces)}
    assert len(table) == 36 and sorted(world.tags) == list(range(len(world.tags)))
    for t in table:   # on a side of the table, below its top and above the floor
        c = world.tags[t]
        assert np.isclose(np.abs(c[:, :2]).max(), world.table_half) and np.all(np.abs(c[:, :2]) <= world.table_half)
        assert np.all((c[:, 2] < world.table_top) & (c[:, 2] > -world.edge / 2))
    errors, n_tags = corner_errors((640, 360), ("z-01", "z-21", "z-10", "z-12"), 12, world, table)
    assert n_tags >= 8
    assert errors.max() < 0.5 and np.median(errors) < 0.05, np.percentile(errors, [50, 95, 100])


def test_rays_reproject_onto_their_pixels():
    """The renderer's rays go through the exact undistorted position of each pixel, out to the
    image's corners, for the strongest lenses of the rig too (k1 near -0.3, where OpenCV's
    fixed-point undistortion alone left rays a third of a pixel off)."""
    cams = true_cameras(make_rig("cube53", resolution=(320, 180), seed=0))
    renderer = Renderer(World(), cams)
    gx, gy = np.meshgrid(np.linspace(-0.5, 319.5, 33), np.linspace(-0.5, 179.5, 19))
    for c in np.argsort(cams.dist[:, 0])[[0, 1, -1]]:   # the two most barrel-like, the most pincushion
        d = renderer.rays(int(c), gx.ravel(), gy.ravel())
        uv = cams.subset([cams.ids[c]]).project(cams.centers[c] + d)[0]
        assert np.abs(uv - np.stack([gx.ravel(), gy.ravel()], axis=1)).max() < 1e-3, cams.dist[c]


def test_rays_that_may_meet_a_sphere_cover_its_whole_image():
    """Per frame only the rays near the hand's and the object's spheres are cast: those must cover
    each sphere's whole image, also off the axis of a pincushion lens (near the corners the image
    reached 1.23 times as far as the circle around the projected centre that was once used)."""
    cams = true_cameras(make_rig("cube53", resolution=(320, 180), seed=0))
    renderer = Renderer(World(), cams, supersample=1)
    surface = np.random.default_rng(0).standard_normal((4000, 3))
    surface /= np.linalg.norm(surface, axis=1, keepdims=True)
    for c in np.argsort(cams.dist[:, 0])[[0, -1]]:   # the most barrel-like and the most pincushion
        w, h = (int(v) for v in cams.size[c])
        corners = np.array([[8.0, 8.0], [w - 9, 8.0], [8.0, h - 9], [w - 9, h - 9], [w / 2, h / 2]])
        centres = cams.centers[c] + renderer.rays(int(c), corners[:, 0], corners[:, 1]) * 0.6
        radii = np.full(len(centres), 0.04)
        near = renderer._near(int(c), centres, radii, (0, 0, w - 1, h - 1)).reshape(len(centres), h, w)
        for m in range(len(centres)):
            uv = np.round(cams.subset([cams.ids[c]]).project(centres[m] + radii[m] * surface)[0]).astype(int)
            uv = uv[(uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)]
            assert near[m, uv[:, 1], uv[:, 0]].all(), (cams.ids[c], corners[m])


def test_tags_json_matches_world_layout():
    world = World()
    doc = world.tags_json()
    assert doc["family"] == "tag36h11" and doc["size"] == world.tag_size
    sides = [np.linalg.norm(np.diff(np.array(c), axis=0), axis=1) for c in doc["tags"].values()]
    assert np.allclose(sides, world.tag_size, atol=1e-9)
    # every tag lies on a wall, and the floor's centre (under the table) carries none
    for corners in world.tags.values():
        c = np.asarray(corners)
        assert np.isclose(np.abs(c).max(), world.edge / 2)
        assert not (np.isclose(c[:, 2], -world.edge / 2).all() and np.abs(c[:, :2]).max() < world.table_half)


def test_lighting_scales_the_image():
    rig = make_rig("cube53", cameras=6, resolution=(160, 90))
    renderer = Renderer(World(), true_cameras(rig))
    full = renderer.render(0, light=1.0).image.mean()
    dim = renderer.render(0, light=0.0).image.mean()
    assert 0.2 < dim / full < 0.3  # only the room's ambient light is left


def test_empty_cube_labels_are_walls():
    rig = make_rig("cube53", cameras=6, resolution=(160, 90))
    out = Renderer(World(), true_cameras(rig)).render(2, labels=True)
    assert out.labels.shape == (90, 160) and (out.labels == LABEL_WALLS).all()


def test_labels_follow_the_majority_of_each_pixel():
    """2x2 rays per pixel tie along edges; the truth must not favour either side of them: the
    hand's 2x2 labels agree with those of 5x5 rays (no ties between two surfaces)."""
    import dataclasses

    from rig.sim.cube import SimulatedCube

    def hand_labels(supersample):
        config = make_rig("cube53", cameras=4, resolution=(320, 180))
        config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, supersample=supersample))
        cube = SimulatedCube(config, "hand", 2.0)
        return np.stack([cube.render(c, cube.t0_ns + 0.5e9, labels=True).labels == 1 for c in range(4)])

    coarse, fine = hand_labels(2), hand_labels(5)
    gained, lost = int((coarse & ~fine).sum()), int((~coarse & fine).sum())
    # of 6875 hand pixels, measured 2 gained / 4 lost; with ties given to the lower label (the
    # hand's, against the walls') 146 / 0
    assert gained + lost < 30, (gained, lost)


@pytest.mark.parametrize("edge", [1.2, 1.25])
def test_textures_of_any_cube_size_build_their_mip_levels(edge):
    """A 1.25 m cube's walls are 625 texels: an odd tile, which the padding to the mip step once
    looked for forever. Every level halves the one before exactly, so tiles stay aligned."""
    world = World(edge=edge, tags_per_wall=5, tag_size=0.16, table_tags=True)
    for atlas in (world.atlas, world.table_atlas):
        shapes = [level.shape[:2] for level in atlas.levels]
        assert all(2 * h == H and 2 * w == W for (H, W), (h, w) in zip(shapes, shapes[1:])), shapes
        assert atlas.stride % 2 ** (len(shapes) - 1) == 0
