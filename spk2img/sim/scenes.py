"""Continuous scenes for the spike-camera simulator (numpy only).

A :class:`Scene` has ``height``, ``width``, ``intensity(t) -> (H, W) float32`` (linear
intensity in [0, 1], docs/format.md, at time ``t`` in frame intervals) and its batched form
``intensities(times) -> (N, H, W)``, which the simulator uses. :class:`MovingImage` moves a
still source image (procedural content or an optional natural photograph) with a smooth
output-to-source coordinate map (translation, rotation, zoom and a non-rigid flow) and samples
it bilinearly; the source is mirrored at its borders, so motion may run for any number of
frames.
"""

from __future__ import annotations

import functools
import importlib.util
from abc import ABC, abstractmethod
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from PIL import Image, ImageDraw, ImageFont

MOTIONS = ("static", "slow", "fast")
"""The motion classes scenes are drawn from by default and scored in."""
TRAINING_MOTIONS = (*MOTIONS, "moderate")
""":data:`MOTIONS` and ``moderate``, the speeds between slow and fast, where real video's faster
windows fall (0.2-0.9 px a spike frame in the real-video validation's fast bin): a class training
can draw (``--speed-mix``), never drawn by default nor scored."""
BRIGHTNESSES = ("dim", "normal", "bright")
SPEED_RANGES = {  # px/frame
    "static": (0.0, 0.0),
    "slow": (0.03, 0.3),
    "fast": (0.5, 3.0),
    "moderate": (0.3, 1.0),
}
MEAN_RANGES = {"dim": (0.03, 0.1), "normal": (0.15, 0.5), "bright": (0.5, 0.85)}  # intensity
CALIBRATION_FRAMES = 64.0  # motion speeds are averaged over frames [0, 64]
SAMPLE_BLOCK = 2**16  # scene samples rendered at once (small: BLAS threads, cache)


class Scene(ABC):
    """Anything the simulator can film: linear intensity in [0, 1] over time (frame intervals).

    ``meta`` is a JSON-able dict describing how the scene was made.
    """

    height: int
    width: int
    meta: dict

    @abstractmethod
    def intensities(self, times: ArrayLike) -> np.ndarray:
        """Intensity at each of ``times`` (N,) as ``(N, H, W) float32`` in [0, 1], read-only."""

    def intensity(self, t: float) -> np.ndarray:
        """Intensity at time ``t`` as ``(H, W) float32`` in [0, 1], read-only."""
        return self.intensities([t])[0]


class StillScene(Scene):
    """A scene that never changes: ``image (H, W)``, linear intensity in [0, 1]."""

    def __init__(self, image: np.ndarray):
        image = np.array(image, np.float32)
        if image.ndim != 2 or not (image.min() >= 0 and image.max() <= 1):
            raise ValueError("a still scene needs an (H, W) image with values in [0, 1]")
        image.flags.writeable = False
        self.height, self.width = image.shape
        self.meta = {"kind": "still", "mean": float(image.mean()), "speed": 0.0}
        self._image = image

    @classmethod
    def uniform(cls, height: int, width: int, level: float) -> StillScene:
        """A flat field of intensity ``level`` (calibration target)."""
        return cls(np.full((height, width), level, np.float32))

    def intensities(self, times: ArrayLike) -> np.ndarray:
        return np.broadcast_to(self._image, (np.size(times), self.height, self.width))


class Motion:
    """A smooth map from output pixel ``(y, x)`` to source coordinates at time ``t``.

    ``p(u, t) = s(τ) R(θ(τ)) u + b(τ) + f(u, τ)`` with ``u`` the offset from the output centre
    and ``τ = clock * t``: rotation ``θ = θ0 + ω τ``; zoom ``log s = log s0 + z sin(Ω τ + φ)``
    (source px per output px, s in [0.6, 1.7]); translation ``b = v τ + a sin(Ω' τ + φ')`` (a
    curved path); ``f`` three plane waves of displacement (non-rigid flow, Jacobian below 0.15
    so the map never folds). ``clock`` scales every rate, so it sets the speed, not the path.
    """

    def __init__(
        self,
        rng: np.random.Generator,
        height: int,
        width: int,
        speed: float,
        mix: tuple[float, float, float, float] | None = None,
    ):
        """Draw a random motion for an ``height x width`` output moving ``speed`` px/frame on
        average over pixels and frames [0, 64]; ``speed = 0`` gives a still random pose.
        ``mix``: shares of the speed from translation, rotation, zoom and flow (None: random,
        Dirichlet(3, 1, 1, 1); ``(1, 0, 0, 0)`` pans the view along a gently curved path)."""
        if not speed >= 0:
            raise ValueError(f"speed must be >= 0 px/frame, got {speed}")
        self.height, self.width = height, width
        size = float(max(height, width))
        radius = 0.4 * float(np.hypot(height, width))  # typical distance from the centre
        weights = rng.dirichlet([3.0, 1.0, 1.0, 1.0]) if mix is None else np.asarray(mix, float)
        w_trans, w_rot, w_zoom, w_flow = weights / weights.sum()
        self.angle0 = float(rng.uniform(-np.pi, np.pi))
        self.angular_velocity = float(rng.choice([-1, 1]) * w_rot / radius)
        self.log_scale0 = float(rng.uniform(np.log(0.8), np.log(1.25)))
        self.zoom_frequency = float(rng.uniform(0.02, 0.1))
        self.zoom_amplitude = float(min(w_zoom / (radius * self.zoom_frequency), np.log(1.3)))
        self.zoom_phase = float(rng.uniform(0, 2 * np.pi))
        direction = rng.uniform(-np.pi, np.pi)
        self.velocity = (w_trans * np.sin(direction), w_trans * np.cos(direction))  # (vy, vx)
        self.sway_frequency = float(rng.uniform(0.02, 0.1))
        sway = rng.uniform(0, 0.5) * w_trans / self.sway_frequency
        self.sway = (sway * np.cos(direction), -sway * np.sin(direction))  # across the path
        self.sway_phase = float(rng.uniform(0, 2 * np.pi))
        wavelength = rng.uniform(0.5, 2.0, 3) * size
        angle = rng.uniform(-np.pi, np.pi, 3)
        k = 2 * np.pi / wavelength
        self.wave_vector = np.stack([k * np.sin(angle), k * np.cos(angle)], 1)  # (3, 2) rad/px
        self.wave_frequency = rng.uniform(0.02, 0.15, 3)  # rad per clock unit
        amplitude = np.minimum(w_flow / (3 * self.wave_frequency), 0.05 / k)  # px
        polarisation = rng.uniform(-np.pi, np.pi, 3)
        self.wave_amplitude = amplitude[:, None] * np.stack(
            [np.sin(polarisation), np.cos(polarisation)], 1
        )  # (3, 2) px, (ay, ax)
        self.wave_phase = rng.uniform(0, 2 * np.pi, 3)
        self.clock = 1.0
        self.clock = 0.0 if speed == 0 else self._calibrated_clock(speed)

    def basis(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Spatial basis ``(9, P)`` of output pixels ``(y, x)`` (any shape, P values): the
        offsets ``u_y, u_x`` from the output centre, 1, and ``sin, cos`` of each wave's phase.
        Source coordinates are ``coefficients(t) @ basis``; same dtype as ``y, x``."""
        uy = np.ravel(y) - (self.height - 1) / 2
        ux = np.ravel(x) - (self.width - 1) / 2
        k = self.wave_vector.astype(uy.dtype)
        phase = k[:, :1] * uy + k[:, 1:] * ux
        return np.concatenate(
            [uy[None], ux[None], np.ones_like(uy)[None], np.sin(phase), np.cos(phase)]
        )

    def coefficients(self, times: ArrayLike) -> np.ndarray:
        """``(N, 2, 9) float64`` weights of :meth:`basis` giving source ``(py, px)`` at ``times``
        (N,): ``p = s R u + b + sum_j a_j sin(k_j u + w_j tau + phi_j)``, ``tau = clock * t``."""
        tau = self.clock * np.atleast_1d(np.asarray(times, np.float64))
        angle = self.angle0 + self.angular_velocity * tau
        zoom = self.zoom_amplitude * np.sin(self.zoom_frequency * tau + self.zoom_phase)
        scale = np.exp(self.log_scale0 + zoom)
        cos, sin = scale * np.cos(angle), scale * np.sin(angle)
        sway = np.sin(self.sway_frequency * tau + self.sway_phase)
        by = self.velocity[0] * tau + self.sway[0] * sway
        bx = self.velocity[1] * tau + self.sway[1] * sway
        wave = self.wave_frequency * tau[:, None] + self.wave_phase  # (N, 3)
        # sin(A + B) = sin A cos B + cos A sin B, with A the spatial phase held in the basis
        ay, ax = self.wave_amplitude[:, 0], self.wave_amplitude[:, 1]
        py = [cos[:, None], sin[:, None], by[:, None], ay * np.cos(wave), ay * np.sin(wave)]
        px = [-sin[:, None], cos[:, None], bx[:, None], ax * np.cos(wave), ax * np.sin(wave)]
        return np.stack([np.concatenate(py, 1), np.concatenate(px, 1)], 1)

    def source_coords(
        self, y: np.ndarray, x: np.ndarray, times: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray]:
        """Source coordinates ``(py, px)``, relative to the source centre, of output pixels
        ``(y, x)`` (shape S) at ``times`` (N,): two ``(N, *S)`` float64 arrays."""
        y, x = np.asarray(y, np.float64), np.asarray(x, np.float64)
        coords = np.einsum("nck,kp->ncp", self.coefficients(times), self.basis(y, x))
        shape = (-1, *y.shape)
        return coords[:, 0].reshape(shape), coords[:, 1].reshape(shape)

    def speed_map(self, y: np.ndarray, x: np.ndarray, times: ArrayLike) -> np.ndarray:
        """Speed ``(N, *S)`` (output px/frame) at which content moves through output pixels
        ``(y, x)`` (shape S) at ``times`` (N,).

        Content at a fixed source point ``p`` sits where ``p(u, t) = p``, so its velocity is
        ``-J⁻¹ ∂p/∂t`` (``J = ∂p/∂u``); both are taken by central differences.
        """
        h, dt = 0.5, 0.05
        times = np.atleast_1d(np.asarray(times, np.float64))

        def diff(a: tuple, b: tuple, step: float) -> list[np.ndarray]:
            return [(pa - pb) / (2 * step) for pa, pb in zip(a, b, strict=True)]

        jyy, jxy = diff(self.source_coords(y + h, x, times), self.source_coords(y - h, x, times), h)
        jyx, jxx = diff(self.source_coords(y, x + h, times), self.source_coords(y, x - h, times), h)
        dpy, dpx = diff(
            self.source_coords(y, x, times + dt), self.source_coords(y, x, times - dt), dt
        )
        det = jyy * jxx - jyx * jxy
        vy = -(jxx * dpy - jyx * dpx) / det
        vx = -(-jxy * dpy + jyy * dpx) / det
        return np.hypot(vy, vx)

    def mean_speed(self, start: float = 0.0, stop: float = CALIBRATION_FRAMES) -> float:
        """Mean speed (px/frame) over a 12x12 grid of output pixels and 9 times in [start, stop]."""
        y, x = np.meshgrid(
            np.linspace(0, self.height - 1, 12), np.linspace(0, self.width - 1, 12), indexing="ij"
        )
        return float(self.speed_map(y, x, np.linspace(start, stop, 9)).mean())

    def _calibrated_clock(self, speed: float) -> float:
        for _ in range(4):  # fixed point: the speed is nearly proportional to the clock
            self.clock *= speed / self.mean_speed()
        return self.clock


class MovingImage(Scene):
    """A still ``source`` image, ``(Hs, Ws) float32`` linear intensity in [0, 1], seen through a
    :class:`Motion` (bilinear sampling, mirrored borders)."""

    def __init__(self, source: np.ndarray, height: int, width: int, motion: Motion, meta: dict):
        self.source = np.ascontiguousarray(source, np.float32)
        if self.source.ndim != 2 or min(self.source.shape) < 2 or self.source.size >= 2**24:
            raise ValueError(f"a source must be 2-D, 2x2 to 16M pixels, got {self.source.shape}")
        self.height, self.width, self.motion, self.meta = height, width, motion, meta
        y, x = np.mgrid[0:height, 0:width].astype(np.float32)
        self.basis = motion.basis(y, x)
        """(9, H * W) float32: the motion's spatial basis at every output pixel."""
        self._still = self._render(np.zeros(1))[0] if motion.clock == 0 else None

    def intensities(self, times: ArrayLike) -> np.ndarray:
        if self._still is not None:
            return np.broadcast_to(self._still, (np.size(times), self.height, self.width))
        return self._render(np.asarray(times, np.float64).ravel())

    def sampling_rows(self, times: np.ndarray) -> np.ndarray:
        """``(2N, 9) float32`` rows whose products with :attr:`basis` are the source ``y`` (the
        first N rows) and ``x`` (the last N) of every output pixel at ``times`` (N,), counted
        from the source's corner."""
        hs, ws = self.source.shape
        coefficients = self.motion.coefficients(times)
        offset = coefficients[:, :, 2] + [(hs - 1) / 2, (ws - 1) / 2]  # from the source corner
        # mirroring repeats every 2 (n - 1) px: fold the offset so float32 keeps its precision
        coefficients[:, :, 2] = np.mod(offset, [2 * (hs - 1), 2 * (ws - 1)])
        rows = coefficients.transpose(1, 0, 2).reshape(-1, coefficients.shape[-1])  # (2N, 9)
        return rows.astype(np.float32)

    def _render(self, times: np.ndarray) -> np.ndarray:
        rows = self.sampling_rows(times)
        n, pixels = len(times), self.height * self.width
        image = np.empty((n, pixels), np.float32)
        step = max(1, SAMPLE_BLOCK // n)  # pixels a block: its temporaries stay in cache
        for start in range(0, pixels, step):
            block = slice(start, start + step)
            # einsum, not BLAS: OpenBLAS threads cost more than they save on blocks this small
            coords = np.einsum("ik,kp->ip", rows, self.basis[:, block])
            py, px = coords.reshape(2, n, -1)  # (N, step) each
            image[:, block] = sample_bilinear(self.source, py, px)
        image = image.reshape(n, self.height, self.width)
        image.flags.writeable = False
        return image


def sample_bilinear(image: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image (Hs, Ws) float32`` at float32 coordinates ``y, x`` (any equal
    shapes), returned as float32 of that shape.

    Coordinates outside the image are mirrored (period ``2 (Hs - 1)``), so the image extends
    continuously forever.
    """
    hs, ws = image.shape
    y, x = _mirror(y, hs), _mirror(x, ws)
    y0 = np.minimum(np.floor(y), np.float32(hs - 2))
    x0 = np.minimum(np.floor(x), np.float32(ws - 2))
    fy, fx = y - y0, x - x0
    i = (y0 * np.float32(ws) + x0).astype(np.intp)  # exact: Hs * Ws < 2**24
    flat = image.ravel()
    top, right = flat[i], flat[i + 1]
    top += fx * (right - top)
    i += ws
    bottom, right = flat[i], flat[i + 1]
    bottom += fx * (right - bottom)
    bottom -= top
    bottom *= fy
    top += bottom
    return top


def _mirror(c: np.ndarray, n: int) -> np.ndarray:
    """Fold coordinates into [0, n - 1] by mirroring: a triangle wave of period 2 (n - 1)."""
    period = np.float32(2 * (n - 1))
    c = c + np.float32(n - 1)
    c -= period * np.floor(c / period)  # in [0, period): cheaper than np.mod for floats
    c -= np.float32(n - 1)
    return np.abs(c, out=c)


# --- source content: (h, w) float32 in [0, 1], not yet tone-mapped -------------------------


def dead_leaves(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Occluding random discs and rotated rectangles (radii 1.5 px to half the image, density
    ~ r^-3, uniform grey levels) with a pink-noise texture inside; drawn at 2x and box-filtered
    for anti-aliased edges."""
    r_min, r_max = 1.5, 0.5 * max(h, w)
    mean_area = 2 * np.pi * r_min**2 * np.log(r_max / r_min)  # E[pi r^2] for p(r) ~ r^-3
    n = int(np.clip(4 * h * w / mean_area, 30, 2000))  # about four layers deep
    radii = np.sort(r_min / np.sqrt(1 - rng.uniform(size=n) * (1 - (r_min / r_max) ** 2)))[::-1]
    cy = 2 * rng.uniform(-radii, h + radii)
    cx = 2 * rng.uniform(-radii, w + radii)
    grey, disc = rng.uniform(size=n), rng.uniform(size=n) < 0.5
    angle, aspect = rng.uniform(0, np.pi, n), rng.uniform(0.3, 1.0, n)
    image = Image.new("F", (2 * w, 2 * h), float(rng.uniform()))
    draw = ImageDraw.Draw(image)
    for i in range(n):  # big leaves first, at the back
        r = 2 * radii[i]
        if disc[i]:
            draw.ellipse((cx[i] - r, cy[i] - r, cx[i] + r, cy[i] + r), fill=float(grey[i]))
            continue
        c, s = np.cos(angle[i]), np.sin(angle[i])
        ry = r * aspect[i]
        corners = [(-r, -ry), (r, -ry), (r, ry), (-r, ry)]
        draw.polygon(
            [(cx[i] + u * c - v * s, cy[i] + u * s + v * c) for u, v in corners],
            fill=float(grey[i]),
        )
    leaves = np.asarray(image.resize((w, h), Image.Resampling.BOX), np.float32)
    texture = rng.uniform(0.0, 0.5) * (pink_noise(rng, h, w) - 0.5)
    return np.clip(leaves * (1 + texture), 0, 1)


def glyphs(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Lines of random text (PIL's default font, random sizes and grey levels) over a smooth
    background: sharp, high-contrast strokes like the printed patterns of real captures."""
    image = (0.3 + 0.4 * pink_noise(rng, h, w, exponent=2.5)) * rng.uniform(0.5, 1.5)
    alphabet = list("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789#%&@")
    y = rng.uniform(-10, 5)
    while y < h:
        size = int(rng.integers(6, max(8, h // 4) + 1))
        text = "".join(rng.choice(alphabet, int(rng.integers(4, 40))))
        mask = Image.new("L", (w, h), 0)
        font = ImageFont.load_default(size=size)
        ImageDraw.Draw(mask).text((float(rng.uniform(-size, w / 3)), y), text, fill=255, font=font)
        alpha = np.asarray(mask, np.float32) / 255
        image = image * (1 - alpha) + rng.uniform() * alpha
        y += size * rng.uniform(0.9, 1.8)
    return np.clip(image, 0, 1).astype(np.float32)


def gratings(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """One to three sine or square-wave gratings (periods 3-40 px, random orientations, some
    chirped), summed and rescaled to [0, 1]."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    total = np.zeros((h, w), np.float32)
    for _ in range(int(rng.integers(1, 4))):
        angle = rng.uniform(0, np.pi)
        u = x * np.float32(np.cos(angle)) + y * np.float32(np.sin(angle))
        period = float(np.exp(rng.uniform(np.log(3), np.log(40))))
        chirp = rng.uniform(-1, 1) / (period * max(h, w)) if rng.uniform() < 0.3 else 0.0
        wave = np.sin(2 * np.pi * (u / period + chirp * u * u) + rng.uniform(0, 2 * np.pi))
        total += np.sign(wave) if rng.uniform() < 0.4 else wave
    return _normalise(total)


def pink_noise(
    rng: np.random.Generator, h: int, w: int, exponent: float | None = None
) -> np.ndarray:
    """1/f^e noise texture (amplitude spectrum exponent ``e``, random in [0.8, 2] if None),
    rescaled to [0, 1] by its 1st and 99th percentiles."""
    e = rng.uniform(0.8, 2.0) if exponent is None else exponent
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.maximum(np.hypot(fy, fx), 1.0 / max(h, w))
    spectrum = np.fft.rfft2(rng.standard_normal((h, w))) / f**e
    return _normalise(np.fft.irfft2(spectrum, s=(h, w)))


def natural_image(rng: np.random.Generator, h: int, w: int) -> np.ndarray | None:
    """A random crop, scaled at random and maybe mirrored, of a public-domain photograph, or
    None if it is not installed.

    The photograph is matplotlib's sample ``grace_hopper.jpg`` (a U.S. Navy photograph, public
    domain); matplotlib is only a dev dependency, so callers fall back to procedural content.
    Grey levels are linearised with gamma 2.2.
    """
    photo = _sample_photo()
    if photo is None:
        return None
    ph, pw = photo.shape
    smallest = max(h / ph, w / pw)  # the scale at which the crop spans the photo
    scale = rng.uniform(smallest, max(smallest, 1.0))
    sh, sw = max(h, round(ph * scale)), max(w, round(pw * scale))
    resized = np.asarray(Image.fromarray(photo).resize((sw, sh), Image.Resampling.LANCZOS))
    top, left = int(rng.integers(0, sh - h + 1)), int(rng.integers(0, sw - w + 1))
    crop = np.clip(resized[top : top + h, left : left + w], 0, 1)
    return crop if rng.uniform() < 0.5 else crop[:, ::-1].copy()


@functools.cache
def _sample_photo() -> np.ndarray | None:
    """matplotlib's ``grace_hopper.jpg`` as linear grey ``float32`` (found without importing
    matplotlib), or None."""
    spec = importlib.util.find_spec("matplotlib")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(spec.submodule_search_locations[0], "mpl-data", "sample_data", "grace_hopper.jpg")
    if not path.is_file():
        return None
    with Image.open(path) as im:
        grey = np.asarray(im.convert("L"), np.float32) / 255
    return grey**2.2


def _normalise(a: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(a, [1, 99])
    return np.clip((a - lo) / max(hi - lo, 1e-6), 0, 1).astype(np.float32)


CONTENT_KINDS = {  # name: (probability weight, generator)
    "natural": (0.25, natural_image),
    "dead_leaves": (0.35, dead_leaves),
    "glyphs": (0.15, glyphs),
    "gratings": (0.1, gratings),
    "pink_noise": (0.15, pink_noise),
}


PROCEDURAL_KINDS = tuple(kind for kind in CONTENT_KINDS if kind != "natural")
"""The content kinds made by code: what training draws (the sample photograph is evaluation
content only)."""


def tone_map(
    content: np.ndarray, rng: np.random.Generator, brightness: str
) -> tuple[np.ndarray, dict]:
    """Map ``content`` in [0, 1] to linear intensity with a random gamma (0.5-2) and black level
    (0-0.1), normalised so the 98th percentile is 1, then brought to a mean drawn from the
    brightness class's range: scaled down if brighter, else raised by a further power (so
    bright scenes saturate ~2% of pixels at most). Returns ``(intensity float32, parameters)``."""
    gamma = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
    black = float(rng.uniform(0.0, 0.1))
    shaped = black + (1 - black) * content.astype(np.float32) ** gamma
    shaped = np.clip(shaped / max(float(np.quantile(shaped, 0.98)), 1e-6), 0, 1)
    target = float(rng.uniform(*MEAN_RANGES[brightness]))
    for _ in range(3):  # mean(x^p) ~ mean(x)^p: a few power steps reach the target
        mean = float(shaped.mean())
        if mean >= target or mean <= 0:
            break
        shaped = shaped ** np.float32(np.log(target) / np.log(mean))
    intensity = shaped * np.float32(min(1.0, target / max(float(shaped.mean()), 1e-6)))
    return intensity, {"gamma": gamma, "black": black, "mean": float(intensity.mean())}


def draw_speed(rng: np.random.Generator, motion: str) -> float:
    """A speed (px/frame) of the motion class, log-uniform in its range (0 for static)."""
    lo, hi = SPEED_RANGES[motion]
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi)))) if hi > 0 else 0.0


def random_scene(
    rng: np.random.Generator,
    height: int,
    width: int,
    motion: str | None = None,
    brightness: str | None = None,
    kinds: tuple[str, ...] = tuple(CONTENT_KINDS),
) -> MovingImage:
    """A random scene: content kind (among ``kinds``, at their weights), motion class
    (``static``, ``slow`` 0.03-0.3 px/frame, ``fast`` 0.5-3 px/frame, log-uniform; or, given,
    ``moderate`` 0.3-1) and brightness class (``dim`` mean intensity 0.03-0.1, ``normal``
    0.15-0.5, ``bright`` 0.5-0.85), each drawn uniformly unless given."""
    motion = motion or str(rng.choice(MOTIONS))
    brightness = brightness or str(rng.choice(BRIGHTNESSES))
    if motion not in TRAINING_MOTIONS or brightness not in BRIGHTNESSES:
        raise ValueError(
            f"motion must be one of {TRAINING_MOTIONS} and brightness one of {BRIGHTNESSES}"
        )
    speed = draw_speed(rng, motion)
    # a source 1.5x the output: zoom and flow seldom reach its mirrored border
    sh, sw = int(np.ceil(1.5 * height)) + 2, int(np.ceil(1.5 * width)) + 2
    kinds = list(kinds)
    weights = np.array([CONTENT_KINDS[k][0] for k in kinds])
    content = None
    while content is None:
        kind = str(rng.choice(kinds, p=weights / weights.sum()))
        content = CONTENT_KINDS[kind][1](rng, sh, sw)
        weights[kinds.index(kind)] = 0.0  # only the natural image can be missing
    source, tone = tone_map(content, rng, brightness)
    meta = {"kind": kind, "motion": motion, "speed": speed, "brightness": brightness, **tone}
    return MovingImage(source, height, width, Motion(rng, height, width, speed), meta)
