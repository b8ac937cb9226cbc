"""Scenes made of natural content: photographs under camera motion with moving foreground
layers, and real video clips with their own motion, interpolated in time.

**Photos.** A crop of a photograph (scaled at random) is the background, seen through a
:class:`~spk2img.sim.scenes.Motion` (translation, rotation, zoom, a perspective-like
non-rigid flow) at a speed of the motion class (static, 0.03-0.3 or 0.5-3 px/frame). Zero to
three foreground layers, each a crop of another photograph cut out by a soft-edged ellipse or
polygon, move with motions of their own over it, so content is occluded and disoccluded.

**Clips.** A video runs far slower than a spike camera (25-60 frames/s against 20-40 kHz), so
``N`` spike frames pass between two video frames. Between frames ``j`` and ``j + 1`` the
intensity at phase ``a`` in [0, 1) is the flow-based interpolation

    I(x, a) = (1 - a) I_j(x - a F_{j->j+1}(x)) + a I_{j+1}(x - (1 - a) F_{j+1->j}(x))

with dense optical flows ``F`` from OpenCV's DIS (the linear-motion approximation of
frame-interpolation methods: each frame is carried along its flow and the two are blended), so
content moves along its real paths rather than cross-fading. ``N`` sets the speed: it is chosen
so the mean flow over the window, divided by ``N``, falls in the motion class's range where the
clip allows (a window spans at most :data:`MAX_INTERVALS` video intervals; slower clips give
slower scenes). docs/training_data.md gives the px/frame distribution this yields.

Intensities are light in [0, 1] by either convention of :mod:`spk2img.sim.sources` (photos
come as light; a clip's frames are made light by the ``light`` argument); each scene is exposed
by a gain that brings its mean to the brightness class (dim 0.03-0.1, normal 0.15-0.5, bright
0.5-0.85), clipping what saturates.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from PIL import Image, ImageDraw

from spk2img.sim.scenes import (
    MEAN_RANGES,
    Motion,
    MovingImage,
    Scene,
    draw_speed,
    sample_bilinear,
)
from spk2img.sim.simulator import FILM_FRAMES
from spk2img.sim.sources import to_light

MAX_LAYERS = 3
LAYER_COUNT_WEIGHTS = (0.3, 0.3, 0.25, 0.15)  # P(0, 1, 2, 3 foreground layers)
MAX_INTERVALS = 24
"""Video frame intervals one 41-frame window may span."""
CLIP_MARGIN = 16
"""Pixels rendered around a clip scene's output so that flows at its border have context."""


def exposure_gain(image: np.ndarray, rng: np.random.Generator, brightness: str) -> float:
    """The gain that brings ``image``'s mean linear intensity to one drawn from the class."""
    target = float(rng.uniform(*MEAN_RANGES[brightness]))
    return target / max(float(image.mean()), 1e-4)


def random_crop(image: np.ndarray, rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A ``(height, width)`` crop of ``image`` at a random scale (down to the scale at which the
    crop spans the image's shorter fit, up to 1:1; smaller images are enlarged), maybe
    mirrored. ``image`` and the result ``float32``."""
    ih, iw = image.shape
    smallest = max(height / ih, width / iw)
    scale = float(rng.uniform(smallest, max(smallest, 1.0)))
    ch, cw = min(ih, round(height / scale)), min(iw, round(width / scale))
    top, left = int(rng.integers(0, ih - ch + 1)), int(rng.integers(0, iw - cw + 1))
    region = image[top : top + ch, left : left + cw]
    if (ch, cw) != (height, width):
        resized = Image.fromarray(region).resize((width, height), Image.Resampling.BILINEAR)
        region = np.asarray(resized, np.float32)
    return region[:, ::-1] if rng.uniform() < 0.5 else region


def soft_shape(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A random ellipse or 3-8-gon filling much of ``(height, width)``, as ``float32`` alpha in
    [0, 1] with anti-aliased edges (drawn at 2x and box-filtered)."""
    mask = Image.new("F", (2 * width, 2 * height), 0.0)
    draw = ImageDraw.Draw(mask)
    if rng.uniform() < 0.5:
        draw.ellipse((0, 0, 2 * width - 1, 2 * height - 1), fill=1.0)
    else:
        n = int(rng.integers(3, 9))
        angles = np.sort(rng.uniform(0, 2 * np.pi, n))
        radius = rng.uniform(0.6, 1.0, n)
        points = [
            (width * (1 + r * np.cos(a)), height * (1 + r * np.sin(a)))
            for r, a in zip(radius, angles, strict=True)
        ]
        draw.polygon(points, fill=1.0)
    return np.asarray(mask.resize((width, height), Image.Resampling.BOX), np.float32)


class LayeredScene(Scene):
    """A background scene with foreground layers composited over it, back to front:
    ``I = I_below (1 - alpha) + content alpha`` per layer; each layer's content and alpha are
    :class:`~spk2img.sim.scenes.MovingImage` s sharing one motion."""

    def __init__(self, background: Scene, layers: list[tuple[MovingImage, MovingImage]], meta):
        self.background, self.layers, self.meta = background, layers, meta
        self.height, self.width = background.height, background.width

    def intensities(self, times: ArrayLike) -> np.ndarray:
        image = np.array(self.background.intensities(times))
        for content, alpha in self.layers:
            a = alpha.intensities(times)
            image += a * (content.intensities(times) - image)
        return np.clip(image, 0, 1, out=image)


def photo_scene(
    rng: np.random.Generator,
    photos: list[np.ndarray],
    height: int,
    width: int,
    motion: str,
    brightness: str,
) -> LayeredScene:
    """A scene from ``photos[0]`` (the background) and, for the foreground layers, the others
    (``(H, W) float32`` linear each); see the module doc."""
    # sources 1.5x the output, as the procedural scenes: zoom and flow seldom reach the border
    sh, sw = int(np.ceil(1.5 * height)) + 2, int(np.ceil(1.5 * width)) + 2
    background = random_crop(photos[0], rng, sh, sw)
    gain = exposure_gain(background[sh // 6 : -sh // 6, sw // 6 : -sw // 6], rng, brightness)
    speed = draw_speed(rng, motion)
    scene = MovingImage(
        np.clip(background * gain, 0, 1), height, width, Motion(rng, height, width, speed), {}
    )
    n_layers = int(rng.choice(MAX_LAYERS + 1, p=LAYER_COUNT_WEIGHTS)) if len(photos) > 1 else 0
    layers = []
    for index in range(n_layers):
        lh = int(rng.uniform(0.25, 0.7) * height) + 2
        lw = int(rng.uniform(0.25, 0.7) * width) + 2
        content = np.zeros((sh, sw), np.float32)
        alpha = np.zeros((sh, sw), np.float32)
        top, left = int(rng.integers(0, sh - lh)), int(rng.integers(0, sw - lw))
        source = photos[1 + index % (len(photos) - 1)]
        patch = random_crop(source, rng, lh, lw) * gain * float(rng.uniform(0.5, 2.0))
        content[top : top + lh, left : left + lw] = np.clip(patch, 0, 1)
        alpha[top : top + lh, left : left + lw] = soft_shape(rng, lh, lw)
        layer_speed = 0.0 if motion == "static" else min(3.0, speed * rng.uniform(0.5, 2.0))
        layer_motion = Motion(rng, height, width, layer_speed)
        layers.append(
            (
                MovingImage(content, height, width, layer_motion, {}),
                MovingImage(alpha, height, width, layer_motion, {}),
            )
        )
    meta = {"kind": "photo", "motion": motion, "speed": speed, "brightness": brightness}
    return LayeredScene(scene, layers, {**meta, "layers": n_layers, "gain": gain})


def dis_flow(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Dense optical flow ``(H, W, 2) float32`` (dx, dy in px) from ``first`` to ``second``,
    ``(H, W) uint8`` each, by OpenCV's DIS (medium preset)."""
    import cv2  # the train extra

    cv2.setNumThreads(1)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(np.ascontiguousarray(first), np.ascontiguousarray(second), None)


class ClipScene(Scene):
    """Video frames ``(n, H + 2m, W + 2m) float32`` linear, shown ``frames_per_interval`` spike
    frames apart from time ``-start`` on, flow-interpolated between them (module doc); the
    output is their ``H x W`` centre (``m`` = :data:`CLIP_MARGIN`)."""

    def __init__(
        self,
        frames: np.ndarray,
        forward: np.ndarray,
        backward: np.ndarray,
        frames_per_interval: float,
        start: float,
        meta: dict,
    ):
        self.frames, self.forward, self.backward = frames, forward, backward
        self.frames_per_interval, self.start, self.meta = frames_per_interval, start, meta
        self.height = frames.shape[1] - 2 * CLIP_MARGIN
        self.width = frames.shape[2] - 2 * CLIP_MARGIN
        m = CLIP_MARGIN
        y, x = np.mgrid[m : m + self.height, m : m + self.width].astype(np.float32)
        self._y, self._x = y, x

    def phases(self, times: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """For each of ``times`` (N,): the video interval ``j`` (``(N,) int``, from frame ``j``
        to ``j + 1``) and the phase ``a`` in it (``(N,) float32`` in [0, 1])."""
        position = (np.ravel(np.asarray(times, np.float64)) + self.start) / self.frames_per_interval
        position = np.clip(position, 0, len(self.frames) - 1)
        interval = np.minimum(position.astype(int), len(self.frames) - 2)
        return interval, (position - interval).astype(np.float32)

    def intensities(self, times: ArrayLike) -> np.ndarray:
        intervals, phases = self.phases(times)
        out = np.empty((len(intervals), self.height, self.width), np.float32)
        m, h, w = CLIP_MARGIN, self.height, self.width
        for i, (j, a) in enumerate(zip(intervals, phases, strict=True)):
            fwd = a * self.forward[j][m : m + h, m : m + w]
            bwd = (1 - a) * self.backward[j][m : m + h, m : m + w]
            before = sample_bilinear(self.frames[j], self._y - fwd[..., 1], self._x - fwd[..., 0])
            after = sample_bilinear(
                self.frames[j + 1], self._y - bwd[..., 1], self._x - bwd[..., 0]
            )
            out[i] = (1 - a) * before + a * after
        return out


def clip_scene(
    rng: np.random.Generator,
    frames: tuple[np.ndarray, ...],
    height: int,
    width: int,
    motion: str,
    brightness: str,
    light: str = "linear",
) -> ClipScene:
    """A scene from a clip's ``frames`` (``(H, W) uint8`` grey levels each), made light by the
    ``light`` convention (:func:`~spk2img.sim.sources.to_light`); module doc."""
    m = CLIP_MARGIN
    fh, fw = frames[0].shape
    rh, rw = height + 2 * m, width + 2 * m
    scale = float(rng.uniform(max(rh / fh, rw / fw), max(rh / fh, rw / fw, 1.0)))
    ch, cw = min(fh, round(rh / scale)), min(fw, round(rw / scale))
    top, left = int(rng.integers(0, fh - ch + 1)), int(rng.integers(0, fw - cw + 1))
    mirror, backwards = rng.uniform() < 0.5, rng.uniform() < 0.5

    def crop(frame: np.ndarray) -> np.ndarray:
        region = Image.fromarray(frame[top : top + ch, left : left + cw])
        region = np.asarray(region.resize((rw, rh), Image.Resampling.BILINEAR))
        return region[:, ::-1].copy() if mirror else region

    # spike frames per video interval: the class's speed where the clip's motion allows (the
    # motion is measured on one pair of frames, the window may span up to MAX_INTERVALS)
    available = min(MAX_INTERVALS, len(frames) - 1)
    probe = int(rng.integers(0, len(frames) - 1))
    motion_px = _mean_motion(dis_flow(crop(frames[probe]), crop(frames[probe + 1])))
    target = draw_speed(rng, motion)
    per_interval = max(FILM_FRAMES / available, motion_px / target) if target > 0 else 1e9
    intervals = min(available, int(np.ceil(FILM_FRAMES / per_interval)) + 1)
    first = int(rng.integers(0, len(frames) - intervals))
    crops = [crop(frame) for frame in frames[first : first + intervals + 1]]
    if backwards:  # motion in either direction
        crops.reverse()
    forward = np.stack([dis_flow(a, b) for a, b in zip(crops, crops[1:], strict=False)])
    backward = np.stack([dis_flow(b, a) for a, b in zip(crops, crops[1:], strict=False)])
    linear = np.stack([to_light(c, light) for c in crops])
    gain = exposure_gain(linear[:, m:-m, m:-m], rng, brightness)
    linear = np.clip(linear * gain, 0, 1)
    span = intervals * per_interval - FILM_FRAMES
    start = float(rng.uniform(0, span)) if target > 0 else 0.0
    speed = _mean_motion(forward) / per_interval
    meta = {"kind": "clip", "motion": motion, "speed": speed, "brightness": brightness}
    meta |= {"frames_per_interval": per_interval, "light": light}
    return ClipScene(linear, forward, backward, per_interval, start, meta)


def _mean_motion(flow: np.ndarray) -> float:
    """Mean flow magnitude (px) over the output part (inside the margin) of ``(..., H, W, 2)``."""
    m = CLIP_MARGIN
    return float(np.hypot(flow[..., 0], flow[..., 1])[..., m:-m, m:-m].mean())
