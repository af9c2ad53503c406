"""What other alignments learnt of a trip's GNSS bias, as priors on its bias chain (per-tile service).

The whole-batch pose graph (Eq. 9, with the bias chain of :func:`pose_graph.add_gnss_bias_chain`)
learns each trip's GNSS offset from every trip it overlaps anywhere, and carries it along the
trip. A tile's alignment sees only the pieces of trips near the tile: its consensus averages
fewer trips, and two tiles settle on different offsets. A *bias message* carries what one tile's
alignment found for a trip into another tile's alignment of the same trip:

- the mean shift ``b = aligned - smoothed`` that the tile gave the trip's frames (the bias,
  since ``S = B g`` with ``B`` a pure shift), at the (weight-averaged) time of those frames;
- its variance: the bias prior's share of the GNSS variance (``rho sigma_base^2``, Eq. 11 at
  weight 1) averaged over the trips that tile aligned together, ``rho sigma_base^2 / n``.

The receiving graph holds the trip's bias at its sub-map nearest in time to the message, with
the message's variance grown by the Gauss-Markov decay over the time between them
(``tau = gnss_bias_tau_s``): a message minutes away says nothing.

Messages are passed tile to tile without removing what the receiver itself sent earlier (no
cavity, as in loopy belief propagation): a tile re-aligned with its neighbours' messages hears
a little of its own earlier consensus back.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B

from csr_core.alignment.params import AlignmentParams
from csr_core.alignment.submaps import Submap
from csr_core.types import TripReconstruction

#: the bias has no heading (as in the bias chain)
_BIAS_YAW_SIGMA_RAD = 1e-4
#: below this decay a message is left out (its variance would be that of no message)
_MIN_DECAY = 0.05


@dataclass(frozen=True)
class GnssBiasMessage:
    """One alignment's estimate of a trip's GNSS bias: ``bias_xy_m`` (world frame, metres) around
    trip time ``t_s``, with ``variance_m2`` per axis."""

    t_s: float
    bias_xy_m: tuple[float, float]
    variance_m2: float


def bias_message(
    timestamps_s: np.ndarray,
    smoothed_xy: np.ndarray,
    aligned_xy: np.ndarray,
    weights: np.ndarray,
    n_trips: int,
    params: AlignmentParams,
) -> GnssBiasMessage | None:
    """The message of one trip's alignment in one tile: ``smoothed_xy`` and ``aligned_xy`` (F, 2)
    the trip's single-trip and aligned positions of the tile's frames, ``weights`` (F,) how much
    the tile's alignment counts for each (its blend weights), ``n_trips`` the trips the tile
    aligned together. ``None`` when no frame has weight."""
    w = np.asarray(weights, float)
    if w.sum() <= 0 or n_trips < 1:
        return None
    shift = (np.asarray(aligned_xy, float) - np.asarray(smoothed_xy, float)) * w[:, None]
    bias = shift.sum(axis=0) / w.sum()
    t = float((np.asarray(timestamps_s, float) * w).sum() / w.sum())
    variance = params.gnss_bias_share * params.gnss_sigma_base_xy_m**2 / n_trips
    return GnssBiasMessage(t, (float(bias[0]), float(bias[1])), float(variance))


def add_bias_messages(
    g: gtsam.NonlinearFactorGraph,
    trip: TripReconstruction,
    group: Sequence[Submap],
    weights: Mapping[int, float],
    messages: Sequence[GnssBiasMessage],
    params: AlignmentParams,
) -> list[int]:
    """Each message as a prior on the bias ``B(i)`` of the trip's sub-map nearest in time (``group``:
    the trip's sub-maps, their biases already in ``g``); returns the indices of the factors added.

    The message is a measurement of the bias at its own time, ``b_msg = phi b_i + n`` (first-order
    Gauss-Markov, ``phi = exp(-dt / tau)``, ``n`` of variance ``(1 - phi^2) sigma_i^2 + var_msg``,
    ``sigma_i`` the bias prior of ``add_gnss_bias_chain``): as a factor on ``b_i`` it is a prior at
    ``b_msg / phi`` with standard deviation ``sqrt(var_msg + (1 - phi^2) sigma_i^2) / phi`` (a
    likelihood, so the chain's own zero-mean prior is not counted twice)."""
    if params.gnss_bias_tau_s <= 0 or not group:
        return []
    t = trip.trip.timestamps_s
    added = []
    for msg in messages:
        s = min(group, key=lambda sm: abs(float(t[sm.anchor_frame]) - msg.t_s))
        phi = float(np.exp(-abs(float(t[s.anchor_frame]) - msg.t_s) / params.gnss_bias_tau_s))
        if phi < _MIN_DECAY:
            continue
        sigma_i2 = params.gnss_bias_share * params.gnss_sigma_base_xy_m**2 / weights[s.submap_id]
        sigma = np.sqrt(msg.variance_m2 + (1.0 - phi**2) * sigma_i2) / phi
        added.append(g.size())
        g.add(
            gtsam.PriorFactorPose2(
                B(s.submap_id),
                gtsam.Pose2(msg.bias_xy_m[0] / phi, msg.bias_xy_m[1] / phi, 0.0),
                gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma, sigma, _BIAS_YAW_SIGMA_RAD])),
            )
        )
    return added
