"""Camera response families for testing response recovery (issue 45 item 4): a pure
gamma, sRGB, filmic curves with toe and shoulder, a rational curve with a hard shoulder
and the demo generator's own, and brackets of a finely printed ramp photographed
through them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..stages.hdr import merge_bracket, recover_response
from .generate import Response
from .pbr import FilmicResponse

__all__ = ["FAMILIES", "against_oracle", "printed_ramp_brackets"]


@dataclass(frozen=True)
class Gamma:
    gamma: float = 2.2

    def __call__(self, X):
        return 255.0 * np.clip(np.asarray(X, float), 0, 1) ** (1 / self.gamma)


@dataclass(frozen=True)
class SRGB:
    def __call__(self, X):
        x = np.clip(np.asarray(X, float), 0, 1)
        return 255.0 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


@dataclass(frozen=True)
class HardShoulder:
    """Rational: linear-ish in log, then a knee that clips hard at 0.8 of the range."""
    knee: float = 0.6

    def __call__(self, X):
        x = np.clip(np.asarray(X, float), 0, None) ** (1 / 2.2)
        y = np.where(x < self.knee, x, self.knee + (x - self.knee) / (1 + 8 * (x - self.knee)))
        return 255.0 * np.clip(y / (self.knee + (1 - self.knee) / (1 + 8 * (1 - self.knee))),
                               0, 1)


FAMILIES = {
    "gamma-2.2": Gamma(2.2),
    "srgb": SRGB(),
    "filmic": FilmicResponse(a=0.2, d=0.3, white=10.0, gamma=2.2),
    "filmic-soft": FilmicResponse(a=0.15, d=0.2, white=6.0, gamma=1.8),
    "hard-shoulder": HardShoulder(),
    "generator": Response(),
}


def _inverse(R, levels: np.ndarray) -> np.ndarray:
    X = np.geomspace(1e-8, 4.0, 40001)
    y = R(X)
    y = y if y.ndim == 1 else y.mean(-1)
    y = np.maximum.accumulate(y + 1e-12 * np.arange(len(y)))
    return np.interp(levels, y, X)


def printed_ramp_brackets(R, stops: float, count: int, seed: int = 5, brackets: int = 3,
                          ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """Brackets of a finely printed exposure ramp (2 x 2 px checks at 60 % contrast,
    radiance over the range ``count`` exposures ``stops`` apart reach) photographed
    through response ``R`` with shot and read noise: (P, H, W, 3) uint8 stacks, times
    (P,), the true radiance (H, W, 3) and the true log response (256, 3)."""
    rng = np.random.default_rng(seed)
    H, W = 200, 300
    ramp = np.exp(np.linspace(np.log(2e-3 * 2 ** (stops * (count - 1) / 2)), np.log(1.5), W))
    yy, xx = np.mgrid[:H, :W]
    print_ = np.where(((xx // 2 + yy // 2) % 2)[..., None] == 0, 1.0, 0.6)
    radiance = ramp[None, :, None] * print_ * np.array([1.0, 0.9, 0.8])
    t = 2.0 ** -(stops * np.arange(count))
    stacks = []
    for _ in range(brackets):
        photos = []
        for ti in t:
            X = radiance * ti
            X = X + np.sqrt(3e-5 * X + 3e-4 ** 2) * rng.standard_normal(X.shape)
            photos.append(np.clip(np.round(np.broadcast_to(R(X), X.shape)), 0, 255)
                          .astype(np.uint8))
        stacks.append(np.stack(photos))
    z = np.arange(256)
    inv = (np.broadcast_to(R.inverse(z[:, None].astype(float)), (256, 3))
           if hasattr(R, "inverse") else np.stack([_inverse(R, z)] * 3, 1))
    g_true = np.log(np.maximum(inv, 1e-12))
    g_true = np.maximum.accumulate(g_true + 1e-9 * z[:, None], axis=0)
    return stacks, t, radiance, g_true


def against_oracle(name: str, R, stops: float, count: int, seed: int = 5) -> dict:
    """The response recovered from :func:`printed_ramp_brackets` and one bracket merged
    with it and with the true response: relative error against the truth (median, 95th
    percentile) of both and their ratios."""
    stacks, t, radiance, g_true = printed_ramp_brackets(R, stops, count, seed)
    g = recover_response(stacks, [t] * len(stacks))

    def error(curve):
        rad, sat, dark = merge_bracket(stacks[0], t, curve)
        ok = ~(sat | dark)
        est, ref = rad[ok], radiance[ok]
        rel = np.abs(est * np.median(ref / est) - ref) / ref
        return float(np.median(rel)), float(np.percentile(rel, 95))

    ours, oracle = error(g), error(g_true)
    return {"family": name, "stops": stops, "exposures": count, "median": ours[0],
            "p95": ours[1], "oracle_median": oracle[0], "oracle_p95": oracle[1],
            "ratio_median": ours[0] / oracle[0], "ratio_p95": ours[1] / oracle[1]}


