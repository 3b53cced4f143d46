"""Tracking outliers: samples that a point tracker got wrong, found from the tracks alone.

A tracker on real video loses a point now and then and reports it, for a frame or two, on another surface point or
in the background: a sample centimetres off where the point is.  A least-squares fit takes such a sample at face
value, and a few of them keep every model — the right one too — far above the noise (on the independent referee's
sideways throw, 0.5 % of the samples moved 3–8 cm made the diagnosis say that nothing explains it: RMSE 4.44 mm
against a noise floor of 1.77 mm).  No model is needed to see them, and none is used here (a model-based rejection
would throw away the very error an effect is missing):

* each point's motion minus the affine motion of its :data:`~.compare.NOISE_NEIGHBOURS` nearest rest neighbours
  (:func:`~.compare.local_affine_residuals`) removes any rigid motion, however abrupt (an impact, a spin), and any
  locally affine deformation; a neighbour further than :data:`TRIM_SIGMAS` × the noise σ from that fit is left
  out of it (a wrong sample would carry its error into its neighbours' residuals, amplified where they lie nearly on
  a surface);
* that residual, divided by its noise standard deviation √(1 + h) (h the fit's leverage), less the median of the
  same point's at its six nearest observed instants (its **spike**), is the noise and the change of the non-affine
  deformation over a few instants for a good sample, and the whole tracking error for a bad one;
* a spike more than :data:`SPIKE_THRESHOLD` robust standard deviations (1.4826·MAD of every spike's components, this
  measurement's own scale), the largest among the instants it was compared with, and more than
  :data:`NEIGHBOUR_RATIO` times its neighbours' at that instant (a deformation the frames do not resolve moves
  neighbouring points alike) is an outlier; the outliers are set aside and the first search's other suspects judged
  again (a good sample next to a run of bad ones has a smaller spike: its median takes them in).  Runs of up to three
  bad instants of one point are found whole.

:func:`find_tracking_outliers` returns them as a (T, N) mask; :func:`~.diagnose.diagnose` treats them as not
observed (as occluded samples) and says so.  Measured on the referee's 20 clean cases and on injected mis-tracks in
docs/diagnosis.md ("Tracking outliers").
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from ..errors import UserError
from .compare import NOISE_NEIGHBOURS, estimate_noise, local_affine_residuals
from .results import json_float

SPIKE_THRESHOLD = 12.0
"""A sample is an outlier when its spike exceeds this many robust standard deviations of the spikes' components.
White noise alone never does; the referee's clean measurements reach 6.2, and soft solids ringing faster than the
frames resolve, tracked through a coarse spring network or MPM grid, more (at 9 those lost up to 12 of 3,600–8,800
samples, at 12 at most 3; docs/diagnosis.md "Tracking outliers")."""
TRIM_SIGMAS = 6.0
"""A neighbour further than this many noise σ from a point's local affine fit is left out of that fit (a wrong
sample would carry its error into its neighbours' residuals).  Chosen over 9 and 12 on injected mis-tracks and on
soft solids ringing faster than the frames: fewer good samples taken with the bad ones, and fewer taken from the
soft solids (docs/diagnosis.md "Tracking outliers")."""
MIN_POINTS = NOISE_NEIGHBOURS + 2
"""Fewest tracked points with which outliers are looked for (each point is judged against its neighbours)."""
NEIGHBOUR_RATIO = 3.0
"""An outlier's spike is more than this many times the median of its neighbours' spikes at that instant: a
deformation the frames do not resolve moves neighbouring points alike (their spikes of one size), a tracking error
one point alone."""
MAX_ROUNDS = 20
"""Searches at most (each sets aside the largest spikes, then looks again)."""
_WINDOW = 3  # instants on each side whose median a sample's residual is compared with
_CHUNK = 256  # points whose spikes are formed at once (memory: 12 × T × chunk × 3 floats)


@dataclass
class TrackingOutliers:
    """Samples a tracker got wrong.

    mask: (T, N) bool, True at an outlier sample; threshold_m: the spike (m, for a fit of unit leverage) above
    which a sample counted; spike_sigma_m: the robust standard deviation (m) of the spikes' components; rounds:
    searches made; noise_sigma: m, :func:`~.compare.estimate_noise` of the tracks as given (NaN where not formed)."""

    mask: np.ndarray
    threshold_m: float
    spike_sigma_m: float
    rounds: int
    noise_sigma: float = math.nan

    @property
    def count(self) -> int:
        return int(self.mask.sum())

    def describe(self, observed_samples: int) -> str:
        points = int(self.mask.any(axis=0).sum())
        share = 100.0 * self.count / max(observed_samples, 1)
        return (f"{self.count} samples ({share:.2g} % of the observed) of {points} tracked points look like tracking "
                f"errors (each more than {1e3 * self.threshold_m:.3g} mm off its neighbours' motion at its instant, "
                "where its own track around it is not): they are treated as not observed (unipixie diagnose "
                "--keep-outliers keeps them)")

    def to_dict(self, times: np.ndarray, listed: int = 200) -> dict:
        """The report's ``tracking_outliers`` block: count, threshold, and the first ``listed`` samples as
        [instant index, time (s), point index]."""
        where = np.argwhere(self.mask)
        return {"count": self.count, "points": int(self.mask.any(axis=0).sum()),
                "threshold_m": json_float(self.threshold_m), "spike_sigma_m": json_float(self.spike_sigma_m),
                "samples": [[int(t), round(float(times[t]), 9), int(i)] for t, i in where[:listed]],
                "listed": int(min(len(where), listed))}


_OFFSETS = (-1, 1, -2, 2, -3, 3, -4, 4, -5, 5, -6, 6)
"""Instants (relative) a sample may be compared with, nearest first: the first 2·:data:`_WINDOW` where its residual
was formed."""


def _normalised_residuals(pos: np.ndarray, rest: np.ndarray, trim: float) -> np.ndarray:
    """(T, N, 3): each sample's local-affine residual (neighbours further than ``trim`` metres from the fit left out)
    divided by √(1 + h), its standard deviation for unit white noise (h the fit's leverage at the point: larger where
    its neighbours lie nearly on a surface or were lost)."""
    resid, factor = local_affine_residuals(pos, rest, NOISE_NEIGHBOURS, trim=trim)
    return resid / np.sqrt(factor)[..., None]


def _shifted(a: np.ndarray, offset: int) -> np.ndarray:
    """``a`` (T, ...) moved along time: out[t] = a[t + offset], NaN past the ends."""
    out = np.full(a.shape, np.nan)
    T = a.shape[0]
    if offset < 0:
        out[-offset:] = a[:T + offset]
    else:
        out[:T - offset] = a[offset:]
    return out


def _size(spike: np.ndarray) -> np.ndarray:
    """(T, N) norms of (T, N, 3) spikes, 0 where not formed."""
    size = np.linalg.norm(spike, axis=-1)
    return np.where(np.isfinite(size), size, 0.0)


def _spikes(pos: np.ndarray, rest: np.ndarray, trim: float) -> tuple[np.ndarray, np.ndarray]:
    """Each sample's normalised residual (:func:`_normalised_residuals`) minus the median of its point's at the
    nearest 2·:data:`_WINDOW` instants where that residual was formed (of :data:`_OFFSETS`, nearest first).

    Returns (spike (T, N, 3), NaN where fewer than three instants were there to compare with; (T, N) the largest
    spike size among those instants, 0 where none).  Points are taken :data:`_CHUNK` at a time (memory)."""
    z = _normalised_residuals(pos, rest, trim)
    T, N, _ = z.shape
    spike = np.full(z.shape, np.nan)
    largest_around = np.zeros((T, N))
    for start in range(0, N, _CHUNK):
        part = slice(start, min(N, start + _CHUNK))
        stack = np.stack([_shifted(z[:, part], o) for o in _OFFSETS])  # (offsets, T, B, 3)
        window = np.isfinite(stack[..., 0])
        window &= np.cumsum(window, axis=0) <= 2 * _WINDOW  # the nearest six
        stack[~window] = np.nan
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices: masked below
            med = np.nanmedian(stack, axis=0)
        chunk = z[:, part] - med
        chunk[window.sum(axis=0) < 3] = np.nan
        spike[:, part] = chunk
        size = _size(chunk)
        around = np.stack([_shifted(size, o) for o in _OFFSETS])
        largest_around[:, part] = np.where(window, around, 0.0).max(axis=0)
    return spike, largest_around


def find_tracking_outliers(positions: np.ndarray, rest_positions: np.ndarray,
                           threshold: float = SPIKE_THRESHOLD) -> TrackingOutliers:
    """The samples of ``positions`` (T, N, 3) metres, NaN = unobserved, that a tracker got wrong (module docstring).

    rest_positions: (N, 3) metres.  With fewer than :data:`MIN_POINTS` points or 6 instants nothing is found.
    A neighbour further from a point's local fit than :data:`TRIM_SIGMAS` × the measurement's noise σ
    (:func:`~.compare.estimate_noise`) is left out of that fit: a wrong sample would otherwise carry its error into
    its neighbours' residuals, amplified where they lie nearly on a surface.
    """
    pos = np.array(positions, dtype=np.float64)
    rest = np.asarray(rest_positions, dtype=np.float64)
    T, N, _ = pos.shape
    mask = np.zeros((T, N), dtype=bool)
    if N < MIN_POINTS or T < 2 * _WINDOW:
        return TrackingOutliers(mask, math.inf, math.nan, 0)
    try:
        noise = estimate_noise(pos, rest)
    except UserError:  # too few consecutive samples to tell noise from anything
        return TrackingOutliers(mask, math.inf, math.nan, 0)
    if not (math.isfinite(noise) and noise > 0):
        return TrackingOutliers(mask, math.inf, math.nan, 0, noise)
    trim = TRIM_SIGMAS * noise  # a neighbour this far from its fit is no good for judging others
    from scipy.spatial import cKDTree

    _, nn = cKDTree(rest).query(rest, k=NOISE_NEIGHBOURS + 1)
    nn = nn[:, 1:]  # (N, k): the neighbours, the point itself left out
    tau, sigma, rounds = math.inf, math.nan, 0
    for rounds in range(1, MAX_ROUNDS + 1):
        spike, largest_around = _spikes(pos, rest, trim)
        comps = spike[np.isfinite(spike)]
        if comps.size < 20:
            break
        size = _size(spike)
        if rounds == 1:  # the scale from the first search: later ones, without the worst samples, would tighten it
            sigma = float(1.4826 * np.median(np.abs(comps - np.median(comps))))
            tau = threshold * sigma
            suspects = size > tau  # later searches judge these again only (setting samples aside thins the fits of
            # the others; a sample that was not suspect with every sample in place does not become one)
        # the largest spike among the instants it was compared with: a good sample next to a run of bad ones has a
        # spike too (its median takes them in), smaller than theirs; it is judged again once they are set aside
        # and well above its neighbours': a deformation the sampling does not resolve (a soft part ringing faster
        # than the frames) moves neighbouring points alike, a tracking error one point alone
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            nearby = np.nanmedian(np.where(size[:, nn] > 0, size[:, nn], np.nan), axis=-1)  # (T, N)
        alone = ~(size <= NEIGHBOUR_RATIO * np.where(np.isfinite(nearby), nearby, 0.0))
        new = suspects & ~mask & (size > tau) & (size >= largest_around) & alone
        if not new.any():
            break
        mask |= new
        pos[new] = np.nan
    return TrackingOutliers(mask, float(tau), sigma, rounds, noise)


def without_samples(measurement, mask: np.ndarray):
    """A copy of ``measurement`` (:class:`~unipixie.core.measurement.Measurement`) with the samples of ``mask`` (T, N)
    bool unobserved (NaN); its rest positions are kept as they were (also where they came from ``positions[0]``)."""
    import dataclasses

    pos = np.array(measurement.positions, dtype=np.float64)
    pos[np.asarray(mask, dtype=bool)] = np.nan
    return dataclasses.replace(measurement, positions=pos, rest_positions=np.array(measurement.rest),
                               warnings=list(measurement.warnings), extra_arrays=dict(measurement.extra_arrays))
