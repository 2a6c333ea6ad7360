"""Headless rendering: a scene's bodies drawn into a NumPy uint8 image (no display, no OpenGL).

Each body is projected orthographically onto a plane of the world ("xz": x right, z up; "xy":
x right, y up; "yz": y right, z up) as the convex hull of its silhouette points (a box's eight
corners, a cylinder's rims, circles around a sphere's centre or a capsule's two end centres; an
``Inertia`` body, imported from MJCF with its mass data only, as its equivalent inertia box, and
not at all where it is fixed) and filled with a flat colour; hinge anchors are drawn as small dots.  Convex fills over each shape's
bounding box are a few NumPy operations, so a frame of a small mechanism costs well under a
millisecond or two: fast enough for ``gymnasium.wrappers.RecordVideo``.

    r = Renderer(scene, plane="xz", center=(0, 0.5), width=3.0, size=(480, 360))
    canvas = r.canvas()
    canvas.circle((1.0, 0.0, 0.5), 0.03, (220, 40, 40))   # world point, radius [m]
    r.draw_bodies(canvas, sim.body_positions()[w], sim.body_rotations()[w])
    frame = canvas.image                                    # (360, 480, 3) uint8
"""
from __future__ import annotations

import numpy as np

from ..sim.scene import REVOLUTE, Scene
from ..sim.shapes import Box, Capsule, Cylinder, Inertia, Sphere

PLANES = {"xz": (0, 2), "xy": (0, 1), "yz": (1, 2)}
PALETTE = [(66, 114, 196), (202, 140, 74), (92, 168, 96), (180, 80, 160), (200, 70, 70), (70, 170, 180)]
FIXED_COLOR = (90, 90, 90)
JOINT_COLOR = (40, 40, 40)
BACKGROUND = (255, 255, 255)


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Vertices of the convex hull of 2D points (n, 2), counter-clockwise (Andrew's monotone chain)."""
    pts = np.unique(np.round(points, 6), axis=0)
    if len(pts) < 3:
        return pts

    def half(seq):
        out = []
        for p in seq:
            while len(out) >= 2 and (out[-1][0] - out[-2][0]) * (p[1] - out[-2][1]) - \
                    (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0]) <= 0:  # fmt: skip
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


class Canvas:
    """An RGB image with a metric view of one plane of the world."""

    def __init__(self, size=(480, 360), plane="xz", center=(0.0, 0.0), width=2.0, background=BACKGROUND):
        if plane not in PLANES:
            raise ValueError(f"plane must be one of {list(PLANES)}, got {plane!r}")
        self.w, self.h = int(size[0]), int(size[1])
        self.axes = PLANES[plane]
        self.center = np.asarray(center, dtype=np.float64)
        self.scale = self.w / float(width)  # px per metre
        if len(set(background)) == 1:  # grey: one memset
            self.image = np.full((self.h, self.w, 3), background[0], dtype=np.uint8)
        else:
            self.image = np.empty((self.h, self.w, 3), dtype=np.uint8)
            self.image[:] = background

    # ---- coordinates
    def project(self, points) -> np.ndarray:
        """World points (..., 3) [m] -> pixel coordinates (..., 2) (column, row)."""
        p = np.asarray(points, dtype=np.float64)
        u = (p[..., self.axes[0]] - self.center[0]) * self.scale + 0.5 * self.w
        v = 0.5 * self.h - (p[..., self.axes[1]] - self.center[1]) * self.scale
        return np.stack([u, v], axis=-1)

    # ---- pixel-space primitives
    def fill_convex(self, pts_px: np.ndarray, color):
        """Fill the convex hull of pixel points (n, 2)."""
        hull = convex_hull(np.asarray(pts_px, dtype=np.float64))
        if len(hull) < 3:
            return
        x0, y0 = np.floor(hull.min(axis=0)).astype(int)
        x1, y1 = np.ceil(hull.max(axis=0)).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, self.w - 1), min(y1, self.h - 1)
        if x0 > x1 or y0 > y1:
            return
        xs = np.arange(x0, x1 + 1) + 0.5
        ys = np.arange(y0, y1 + 1)[:, None] + 0.5
        inside = np.ones((y1 - y0 + 1, x1 - x0 + 1), dtype=bool)
        a, b = hull, np.roll(hull, -1, axis=0)
        for (ax, ay), (bx, by) in zip(a, b):  # counter-clockwise in (u, v): inside is left of each edge
            inside &= (bx - ax) * (ys - ay) - (by - ay) * (xs - ax) >= 0
        self.image[y0 : y1 + 1, x0 : x1 + 1][inside] = color

    def fill_circle_px(self, c, r, color):
        x0, y0 = int(max(np.floor(c[0] - r), 0)), int(max(np.floor(c[1] - r), 0))
        x1, y1 = int(min(np.ceil(c[0] + r), self.w - 1)), int(min(np.ceil(c[1] + r), self.h - 1))
        if x0 > x1 or y0 > y1:
            return
        xs = np.arange(x0, x1 + 1) + 0.5 - c[0]
        ys = np.arange(y0, y1 + 1)[:, None] + 0.5 - c[1]
        self.image[y0 : y1 + 1, x0 : x1 + 1][xs * xs + ys * ys <= r * r] = color

    # ---- world-space primitives
    def circle(self, point, radius, color):
        """A disc at a world point, radius [m] (at least one pixel)."""
        self.fill_circle_px(self.project(point), max(radius * self.scale, 1.0), color)

    def segment(self, p0, p1, width, color):
        """A thick line between world points, width [m] (at least one pixel)."""
        a, b = self.project(p0), self.project(p1)
        d = b - a
        n = np.array([-d[1], d[0]]) / max(np.hypot(*d), 1e-9) * max(0.5 * width * self.scale, 0.5)
        self.fill_convex(np.stack([a + n, a - n, b - n, b + n]), color)

    def hline(self, z, color, width_px=1):
        """A horizontal line across the image at height z [m] (second plane axis)."""
        v = int(round(0.5 * self.h - (z - self.center[1]) * self.scale))
        lo, hi = max(v - width_px // 2, 0), min(v + (width_px + 1) // 2, self.h)
        if lo < hi:
            self.image[lo:hi] = color


def inertia_box_corners(shape: Inertia) -> np.ndarray:
    """(8, 3) corners [m, body frame] of the uniform box with the mass and the principal inertias of
    ``shape`` about its centre of mass, on the principal axes: half-extents
    a_i = √(3(I_j + I_k − I_i)/(2m)) (a rod of length L gives L/2 along it)."""
    inertia = np.asarray(shape.inertia, dtype=np.float64).reshape(3, 3)
    moments, axes = np.linalg.eigh(0.5 * (inertia + inertia.T))
    half = np.sqrt(np.maximum(1.5 * (moments.sum() - 2.0 * moments) / shape.mass, 0.0))
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    return np.asarray(shape.com, dtype=np.float64) + (signs * half) @ axes.T


def _circle_points(n=20):
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.stack([np.cos(t), np.sin(t)], axis=1)


class Renderer:
    """Draws the bodies of ``scene`` (and dots at its joint anchors) onto canvases."""

    def __init__(self, scene: Scene, plane="xz", center=(0.0, 0.0), width=2.0, size=(480, 360), colors=None):
        self.scene, self.plane, self.center, self.width, self.size = scene, plane, center, width, size
        self.local_points, self.circles, self.colors = [], [], []
        free = 0
        for k, body in enumerate(scene.bodies):
            s = body.shape
            pts, circ = np.zeros((0, 3)), []
            if isinstance(s, Box):
                hx, hy, hz = s.half_extents
                pts = np.array([[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
            elif isinstance(s, Cylinder):
                c = _circle_points(16) * s.radius
                pts = np.concatenate([np.c_[c, np.full(16, z)] for z in (-s.half_height, s.half_height)])
            elif isinstance(s, Capsule):
                circ = [(np.array([0.0, 0.0, z]), s.radius) for z in (-s.half_height, s.half_height)]
            elif isinstance(s, Sphere):
                circ = [(np.zeros(3), s.radius)]
            elif isinstance(s, Inertia):
                # a fixed imported body stands in for the world (its mass data carry no shape)
                pts = np.zeros((0, 3)) if body.fixed else inertia_box_corners(s)
            else:  # unknown shape: a dot of its bounding radius
                circ = [(np.zeros(3), s.bounding_radius())]
            self.local_points.append(pts)
            self.circles.append(circ)
            if colors is not None:
                self.colors.append(tuple(colors[k]))
            elif body.fixed:
                self.colors.append(FIXED_COLOR)
            else:
                self.colors.append(PALETTE[free % len(PALETTE)])
            if not body.fixed:
                free += 1
        # hinge anchors in the first body's frame (a slider's anchor is no fixed point of either body)
        self.anchors = [(j.body_a, scene.bodies[j.body_a].to_local_point(j.anchor)) for j in scene.joints
                        if j.kind == REVOLUTE]  # fmt: skip
        self._unit = _circle_points(20)

    def canvas(self) -> Canvas:
        return Canvas(self.size, self.plane, self.center, self.width)

    def draw_bodies(self, canvas: Canvas, positions, rotations, joints=True):
        """Draw every body at its pose: positions (num_bodies, 3), rotations (num_bodies, 3, 3)."""
        positions, rotations = np.asarray(positions, dtype=np.float64), np.asarray(rotations, dtype=np.float64)
        if not np.all(np.isfinite(positions)) or not np.all(np.isfinite(rotations)):
            return  # a failed world: nothing sensible to draw
        for k in range(len(self.local_points)):
            p, A = positions[k], rotations[k]
            pts2 = []
            if len(self.local_points[k]):
                pts2.append(canvas.project(p + self.local_points[k] @ A.T))
            for c, r in self.circles[k]:
                pts2.append(canvas.project(p + A @ c) + self._unit * (r * canvas.scale))
            if pts2:
                canvas.fill_convex(np.concatenate(pts2), self.colors[k])
        if joints:
            dot = max(0.012 * self.width, 2.0 / canvas.scale)
            for b, local in self.anchors:
                canvas.circle(positions[b] + rotations[b] @ local, dot * 0.5, JOINT_COLOR)

    def frames(self, positions, rotations, worlds, extras=None) -> tuple:
        """One frame (H, W, 3) uint8 per world in ``worlds``: its bodies from ``positions`` (W, bodies,
        3) and ``rotations`` (W, bodies, 3, 3), then ``extras(canvas, world)`` (a task's marks)."""
        out = []
        for w in worlds:
            canvas = self.canvas()
            self.draw_bodies(canvas, positions[w], rotations[w])
            if extras is not None:
                extras(canvas, w)
            out.append(canvas.image)
        return tuple(out)
