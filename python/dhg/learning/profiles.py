"""Demonstration profiles: what the experts did at each depth along the planned path.

From a dataset's expert episodes (``dhg synth`` or ``dhg record`` of real people alike), per bin
of depth along A→B: the experts' lateral deviation from the line (mean and spread), their feed
rate while the drill ran and advanced, the thrust they felt (the device force against the drill
axis), and where their first cortex gave way (the first record whose burr front left cortical
bone for something softer). ``dhg train`` stores the profiles in the model file's metadata
(``dhg.json``, key ``profiles``), so a server given ``--model`` carries what guidance needs.

The corridor's stiffness per depth follows the experts' agreement, stiff where they agree and
compliant where they vary: proportional to the precision ``1/σ²`` of their lateral position (σ the
RMS distance of their tips from their mean lateral position in that bin), as
in minimal-intervention control from demonstrations (Calinon, Sardellitti & Caldwell 2010;
Ewerton et al. 2018), scaled so that the typical expert spread gets the fixed corridor's 400 N/m
and clamped to 100–400 N/m (the Touch renders at most about 400 N/m stably).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from dhg.core.errors import InvalidInputError
from dhg.core.layers import Layer
from dhg.core.path import PlannedPath
from dhg.core.session import GUIDANCE_DEFAULTS
from dhg.data.dataset import Dataset

__all__ = ["CORRIDOR_N_PER_M", "DemoProfiles", "build_profiles"]

CORRIDOR_N_PER_M = (100.0, float(GUIDANCE_DEFAULTS["corridor_stiffness_n_per_m"]))
"""Range of the corridor stiffness a profile sets (N/m): at most the fixed corridor's (the core's
default, 400 N/m), at least a quarter of it (the project's choice)."""
MIN_RECORDS_PER_BIN = 3
"""Bins with fewer expert records than this take their neighbours' values."""


@dataclass
class DemoProfiles:
    """Per depth bin (``bin_m`` wide, from A), the experts' statistics (SI units, device newtons)."""

    bin_m: float
    depth_m: list[float]
    """Bin centres (m from A)."""
    records: list[int]
    """Expert records in each bin."""
    lateral_mean_m: list[float]
    """Mean distance of the experts' tip from the line (m)."""
    lateral_spread_m: list[float]
    """RMS distance of the experts' tip from their mean lateral position (m)."""
    feed_mean_m_s: list[float]
    feed_sd_m_s: list[float]
    thrust_mean_n: list[float]
    thrust_sd_n: list[float]
    """Device force against the drill axis (N)."""
    breakthrough_depths_m: list[float]
    """Each expert episode's first breakthrough (tip depth, m)."""
    corridor_n_per_m: list[float]
    """Corridor stiffness per bin (N/m), from the lateral spread."""
    episodes: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DemoProfiles:
        try:
            p = cls(**d)
        except TypeError as exc:
            raise InvalidInputError(f"not demonstration profiles: {exc}") from None
        if not (p.bin_m > 0 and len(p.corridor_n_per_m) == len(p.depth_m) > 0):
            raise InvalidInputError("demonstration profiles need a positive bin and one stiffness per bin")
        return p

    @property
    def breakthrough_m(self) -> tuple[float, float] | None:
        """Mean and SD of the experts' first breakthrough depth (m), if any broke through."""
        b = np.array(self.breakthrough_depths_m)
        return (float(b.mean()), float(b.std())) if len(b) else None


def build_profiles(
    ds: Dataset, bin_m: float = GUIDANCE_DEFAULTS["corridor_profile_bin_m"], skill: str = "expert"
) -> DemoProfiles:
    """The demonstration profiles of ``ds``'s episodes of ``skill`` (see the module docs)."""
    if not (np.isfinite(bin_m) and bin_m > 0):
        raise InvalidInputError(f"bin_m must be positive, got {bin_m}")
    planned = ds.card.get("planned_path")
    if planned is None:
        raise InvalidInputError(f"{ds.path}: the dataset card names no planned path; profiles are per depth along it")
    path = PlannedPath.from_dict(planned)
    episodes = ds.select(skill)
    if not episodes:
        raise InvalidInputError(f"{ds.path}: no {skill} episodes to build profiles from")
    n_bins = max(1, int(np.ceil(path.length_m / bin_m)))
    d = path.direction
    depth, lateral, offsets, feed, thrust = [], [], [], [], []
    breakthroughs = []
    for ep in episodes:
        f = ep.features
        tips, dep, layer = f[:, 3:6], f[:, 7], f[:, 6]
        inside = (dep >= 0) & (dep < path.length_m)
        lat = path.lateral_deviation(tips)
        v = np.gradient(dep, ep.times_s) if len(dep) > 1 else np.zeros_like(dep)
        advancing = ep.drill_on & (v > 0)
        depth.append(dep[inside])
        lateral.append(lat[inside])
        rel = tips[inside] - path.entry_m
        offsets.append(rel - np.outer(rel @ d, d))
        feed.append(np.where(advancing, v, np.nan)[inside])
        thrust.append(-(f[:, 0:3] @ d)[inside])
        was_cortex = np.maximum.accumulate(layer == Layer.CORTICAL)
        left = np.flatnonzero(was_cortex & (layer != Layer.CORTICAL) & (dep > 0))
        if len(left):
            breakthroughs.append(float(dep[left[0]]))
    dep_all, lat_all = np.concatenate(depth), np.concatenate(lateral)
    feed_all, thr_all = np.concatenate(feed), np.concatenate(thrust)
    idx = np.minimum((dep_all / bin_m).astype(int), n_bins - 1)

    def stat(values: np.ndarray, fn: Any) -> list[float]:
        out = np.full(n_bins, np.nan)
        for b in range(n_bins):
            v = values[(idx == b) & np.isfinite(values)]
            if len(v) >= MIN_RECORDS_PER_BIN:
                out[b] = fn(v)
        return _fill(out)

    off_all = np.concatenate(offsets)
    spread = np.full(n_bins, np.nan)
    for b in range(n_bins):
        o = off_all[idx == b]
        if len(o) >= MIN_RECORDS_PER_BIN:
            spread[b] = np.sqrt(np.mean(np.sum((o - o.mean(axis=0)) ** 2, axis=1)))
    lat_sd = np.array(_fill(spread))
    counts = np.bincount(idx, minlength=n_bins)[:n_bins]
    reference = float(np.median(lat_sd))
    k_lo, k_hi = CORRIDOR_N_PER_M
    with np.errstate(divide="ignore"):
        k = np.clip(k_hi * (reference / np.maximum(lat_sd, 1e-6)) ** 2, k_lo, k_hi)
    return DemoProfiles(
        bin_m=float(bin_m),
        depth_m=[float((b + 0.5) * bin_m) for b in range(n_bins)],
        records=[int(c) for c in counts],
        lateral_mean_m=stat(lat_all, np.mean),
        lateral_spread_m=[float(v) for v in lat_sd],
        feed_mean_m_s=stat(feed_all, np.mean),
        feed_sd_m_s=stat(feed_all, np.std),
        thrust_mean_n=stat(thr_all, np.mean),
        thrust_sd_n=stat(thr_all, np.std),
        breakthrough_depths_m=breakthroughs,
        corridor_n_per_m=[float(v) for v in k],
        episodes=len(episodes),
    )


def _fill(values: np.ndarray) -> list[float]:
    """Empty bins (NaN) take the nearest filled bin's value; all empty: zeros."""
    ok = np.flatnonzero(np.isfinite(values))
    if not len(ok):
        return [0.0] * len(values)
    at = np.arange(len(values))
    nearest = ok[np.abs(at[:, None] - ok[None, :]).argmin(axis=1)]
    return [float(v) for v in values[nearest]]
