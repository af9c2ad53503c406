"""Random routes through a world's lane graph and the true 10 Hz trajectory driven along them.

A route is a random walk over successor edges, with lane changes (smooth lateral blends of
``lane_change_duration_s`` at the legal speed) where a neighbour lane exists. The speed profile
takes the legal speed times a per-trip driver factor, caps it by lateral acceleration on
curves, stops at some signalised stop lines, and respects acceleration limits.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import networkx as nx
import numpy as np

from csr_core.sim import geometry as geo
from csr_core.sim.profiles import TrafficParams
from csr_core.sim.world import LEFT, RIGHT, SUCCESSOR, SimulationError, World

log = logging.getLogger(__name__)

PATH_STEP_M = 0.5
_JUNCTION_TYPES = ("urban_junction", "roundabout", "turnaround")


@dataclass(frozen=True)
class Route:
    path_xy: np.ndarray  # (M, 2) world, PATH_STEP_M spacing
    speed_limit_mps: np.ndarray  # (M,)
    stops_s_m: np.ndarray  # (K,) arclength of stops
    stops_wait_s: np.ndarray  # (K,)
    lane_ids: tuple[int, ...]


@dataclass(frozen=True)
class Drive:
    timestamps_s: np.ndarray  # (N,)
    poses_xyyaw_world: np.ndarray  # (N, 3) true world_T_vehicle
    speed_mps: np.ndarray  # (N,)


def _edges(world: World, lane: int, kinds: tuple[str, ...]) -> list[int]:
    g = world.lane_graph
    return sorted(v for _, v, d in g.out_edges(lane, data=True) if d["kind"] in kinds)


def _lane_length(world: World, lane: int) -> float:
    return float(geo.arclength_m(world.lane_graph.nodes[lane]["centerline_xy"])[-1])


def _start_lanes(world: World) -> list[int]:
    """Visible road lanes longer than 20 m in the well-connected parts of the lane graph
    (strongly connected components holding at least a quarter of the largest one's lane length),
    so that routes do not ping-pong on an isolated stub of a real map."""
    g = world.lane_graph
    components = [sorted(c) for c in nx.strongly_connected_components(g)]
    size = [sum(_lane_length(world, n) for n in c if g.nodes[n]["visible"]) for c in components]
    good = {n for c, sz in zip(components, size, strict=True) if sz >= 0.25 * max(size) for n in c}
    lanes = [
        n
        for n in sorted(g.nodes)
        if n in good
        and g.nodes[n]["visible"]
        and g.nodes[n]["road_type"] not in _JUNCTION_TYPES
        and _lane_length(world, n) > 20.0
    ]
    return lanes or sorted(good)


def random_route(
    world: World, rng: np.random.Generator, length_m: float, params: TrafficParams, max_tries: int = 20
) -> Route:
    """Random walk of about ``length_m`` (shorter only if every try hits a dead end)."""
    best: Route | None = None
    starts = _start_lanes(world)
    for _ in range(max_tries):
        route = _walk(world, rng, length_m, params, starts[int(rng.integers(len(starts)))])
        if best is None or len(route.path_xy) > len(best.path_xy):
            best = route
        if geo.arclength_m(best.path_xy)[-1] >= length_m - 1.0:
            break
    if best is None or len(best.path_xy) < 3:
        raise SimulationError(f"world {world.name!r}: no drivable route found in {max_tries} tries")
    return best


def _walk(world: World, rng: np.random.Generator, length_m: float, params: TrafficParams, lane: int) -> Route:
    g = world.lane_graph
    pieces: list[np.ndarray] = []
    limits: list[np.ndarray] = []
    stops: list[tuple[float, float]] = []
    lanes = [lane]
    total = 0.0
    s0 = float(rng.uniform(0.0, 0.6)) * _lane_length(world, lane)

    def take(points_xy: np.ndarray, speed: float) -> None:
        nonlocal total
        if len(points_xy) < 2:
            return
        pieces.append(points_xy)
        limits.append(np.full(len(points_xy), speed))
        total += float(geo.arclength_m(points_xy)[-1])

    while total < length_m:
        node = g.nodes[lane]
        c, speed = node["centerline_xy"], node["speed_mps"]
        lane_len = float(geo.arclength_m(c)[-1])
        change_len = max(speed * params.lane_change_duration_s, 20.0)
        neighbours = _edges(world, lane, (LEFT, RIGHT))
        room = lane_len - s0 - change_len - 15.0
        if neighbours and room > 10.0 and rng.random() < params.lane_change_prob:
            target = neighbours[int(rng.integers(len(neighbours)))]
            s_c = s0 + float(rng.uniform(5.0, room))
            take(geo.cut(c, s0, s_c, PATH_STEP_M), speed)
            ct = g.nodes[target]["centerline_xy"]
            a_xy = geo.cut(c, s_c, s_c + change_len, PATH_STEP_M)
            s_t = float(geo.arclength_m(ct)[np.argmin(np.linalg.norm(ct - a_xy[0], axis=1))])
            b_xy = geo.interpolate_at(ct, s_t + geo.arclength_m(a_xy))
            u = geo.arclength_m(a_xy) / change_len
            w = (0.5 - 0.5 * np.cos(np.pi * np.clip(u, 0, 1)))[:, None]
            take((1 - w) * a_xy + w * b_xy, speed)
            lane, s0 = target, s_t + change_len
            lanes.append(lane)
            continue
        take(geo.cut(c, s0, lane_len, PATH_STEP_M), speed)
        stop_before = node.get("stop_line_before_end_m")
        successors = _edges(world, lane, (SUCCESSOR,))
        if stop_before is not None and successors and rng.random() < params.red_light_prob:
            stops.append((total - stop_before - 1.0, float(rng.uniform(*params.red_light_wait_s))))
        if not successors:
            break
        lane, s0 = successors[int(rng.integers(len(successors)))], 0.0
        lanes.append(lane)

    path = np.vstack(pieces)
    limit = np.concatenate(limits)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(path, axis=0), axis=1) > 0.05])
    path, limit = path[keep], limit[keep]
    path = _smooth(path, 7)
    s = geo.arclength_m(path)
    s_new = np.arange(0.0, min(s[-1], length_m), PATH_STEP_M)
    path_rs = geo.interpolate_at(path, s_new)
    limit_rs = limit[np.clip(np.searchsorted(s, s_new), 0, len(limit) - 1)]
    stops_arr = np.array([st for st in stops if 10.0 < st[0] < s_new[-1] - 10.0]).reshape(-1, 2)
    return Route(path_rs, limit_rs, stops_arr[:, 0], stops_arr[:, 1], tuple(lanes))


_LOOPS: dict[str, dict[int, tuple[float, list[int]]]] = {}  # by world name (worlds are fixed)


def _shortest_loops(world: World) -> dict[int, tuple[float, list[int]]]:
    """For each visible lane on a cycle of successor edges: the shortest such cycle through it
    (its length in metres of centreline, its lanes starting with that one)."""
    g = world.lane_graph
    length = {n: _lane_length(world, n) for n in g.nodes}
    succ = nx.DiGraph()
    succ.add_nodes_from(g.nodes)
    succ.add_weighted_edges_from(
        (u, v, length[v]) for u, v, d in g.edges(data=True) if d["kind"] == SUCCESSOR
    )
    out: dict[int, tuple[float, list[int]]] = {}
    for lane in sorted(g.nodes):
        if not g.nodes[lane]["visible"]:
            continue
        dist, paths = nx.single_source_dijkstra(succ, lane)
        # a cycle closes through a predecessor of the lane reached from it
        best: tuple[float, list[int]] | None = None
        for pred in succ.predecessors(lane):
            if pred in dist and (best is None or dist[pred] + length[lane] < best[0]):
                best = (dist[pred] + length[lane], list(paths[pred]))
        if best is not None:
            out[lane] = best
    return out


def looping_route(world: World, rng: np.random.Generator, length_m: float, params: TrafficParams) -> Route:
    """A trip that laps the shortest loop of the lane graph through a random start lane after an
    approach of ``loop_approach_m`` along the lanes leading into it: a standstill of
    ``start_standstill_s`` at the start and ``loop_stops_per_km`` stops anywhere (queues, red
    lights). Its GNSS/odometry chords longer than a loop are all in the approach, the case a
    trip-level odometry calibration must not be fooled by. A world without a loop (a one-way
    road) gives a :func:`random_route`."""
    g = world.lane_graph
    loops = _LOOPS.get(world.name)
    if loops is None:
        loops = _LOOPS[world.name] = _shortest_loops(world)
    if not loops:  # a one-way road (a motorway section): no loop to lap, an ordinary route
        log.info("world %r has no loop in its lane graph: a random route instead", world.name)
        return random_route(world, rng, length_m, params)
    shortest = min(length for length, _ in loops.values())
    # the loops within twice the shortest: the small blocks, rings and turnarounds of the map
    small = sorted(k for k, (length, _) in loops.items() if length <= 2.0 * shortest)
    entry = small[int(rng.integers(len(small)))]
    loop = loops[entry][1]
    # approach: the lanes leading into the entry lane, walked backwards, cut to its length
    approach_m = float(rng.uniform(*params.loop_approach_m))
    back: list[int] = []
    lane, have = entry, 0.0
    while have < approach_m:
        preds = sorted(
            u for u, _, d in g.in_edges(lane, data=True) if d["kind"] == SUCCESSOR and u not in loop
        )
        if not preds:
            break
        lane = preds[int(rng.integers(len(preds)))]
        back.append(lane)
        have += _lane_length(world, lane)
    pieces = [g.nodes[n]["centerline_xy"] for n in reversed(back)]
    limits = [np.full(len(p), g.nodes[n]["speed_mps"]) for p, n in zip(pieces, reversed(back), strict=True)]
    total = sum(float(geo.arclength_m(p)[-1]) for p in pieces)
    lap_lanes = loop
    while total < length_m + approach_m:
        for n in lap_lanes:
            c = g.nodes[n]["centerline_xy"]
            pieces.append(c)
            limits.append(np.full(len(c), g.nodes[n]["speed_mps"]))
            total += float(geo.arclength_m(c)[-1])
    path = np.vstack(pieces)
    limit = np.concatenate(limits)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(path, axis=0), axis=1) > 0.05])
    path, limit = _smooth(path[keep], 7), limit[keep]
    s = geo.arclength_m(path)
    start = max(0.0, min(have, s[-1]) - approach_m)
    s_new = np.arange(start, min(s[-1], start + length_m), PATH_STEP_M)
    path_rs = geo.interpolate_at(path, s_new)
    limit_rs = limit[np.clip(np.searchsorted(s, s_new), 0, len(limit) - 1)]
    run = float(s_new[-1] - s_new[0])
    n_stops = int(rng.poisson(params.loop_stops_per_km * run / 1000.0))
    stop_s = np.sort(rng.uniform(10.0, max(run - 10.0, 10.0), n_stops))
    stop_wait = rng.uniform(*params.red_light_wait_s, n_stops)
    stop_s = np.r_[0.0, stop_s]
    stop_wait = np.r_[float(rng.uniform(*params.start_standstill_s)), stop_wait]
    return Route(path_rs, limit_rs, stop_s, stop_wait, tuple([*reversed(back), *loop]))


def _smooth(points_xy: np.ndarray, window: int) -> np.ndarray:
    """Moving average keeping the end points (removes kinks at lane joins)."""
    if len(points_xy) <= window:
        return points_xy
    kernel = np.ones(window) / window
    pad = window // 2
    padded = np.vstack([np.repeat(points_xy[:1], pad, 0), points_xy, np.repeat(points_xy[-1:], pad, 0)])
    return np.column_stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(2)])


def drive(route: Route, rng: np.random.Generator, params: TrafficParams) -> Drive:
    """The true trajectory along ``route`` at ``frame_rate_hz``, starting and ending at rest."""
    # slow lateral wander of the driver inside the lane
    s = geo.arclength_m(route.path_xy)
    wander = np.zeros_like(s)
    if params.lane_wander_sigma_m > 0:
        for wavelength in (80.0, 190.0, 410.0):
            wander += np.sin(2 * np.pi * s / wavelength + rng.uniform(0, 2 * np.pi))
        wander *= params.lane_wander_sigma_m / np.sqrt(1.5)
        wander *= np.clip(np.minimum(s, s[-1] - s) / 30.0, 0, 1)
    path = geo.offset(route.path_xy, wander) if params.lane_wander_sigma_m > 0 else route.path_xy
    path = _smooth(path, 9)
    s = geo.arclength_m(path)
    ds = np.diff(s)

    factor = float(rng.uniform(*params.driver_speed_factor))
    kappa = np.abs(geo.curvature_1pm(path))
    kappa = np.convolve(kappa, np.ones(9) / 9, mode="same")
    v = np.minimum(
        route.speed_limit_mps * factor, np.sqrt(params.max_lateral_accel_mps2 / np.maximum(kappa, 1e-5))
    )
    v[0] = v[-1] = 0.0
    stop_idx = np.clip(np.searchsorted(s, route.stops_s_m), 0, len(s) - 2)  # 0: a standstill at the start
    v[stop_idx] = 0.0
    for i in range(1, len(v)):  # acceleration limit
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * params.max_accel_mps2 * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):  # braking limit
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * params.max_decel_mps2 * ds[i]))
    dt = ds / np.maximum((v[:-1] + v[1:]) / 2.0, 0.05)
    t_of_s = np.concatenate([[0.0], np.cumsum(dt)])
    # waits at stops: the same arclength twice, ``wait`` seconds apart
    s_aug, t_aug = s.copy(), t_of_s.copy()
    for i, wait in sorted(zip(stop_idx.tolist(), route.stops_wait_s.tolist(), strict=True), reverse=True):
        t_aug[i + 1 :] += wait
        s_aug = np.insert(s_aug, i + 1, s_aug[i])
        t_aug = np.insert(t_aug, i + 1, t_aug[i] + wait)
    dt_frame = 1.0 / params.frame_rate_hz
    timestamps = np.arange(int(np.floor(t_aug[-1] / dt_frame)) + 1) * dt_frame
    s_frames = np.interp(timestamps, t_aug, s_aug)
    xy = geo.interpolate_at(path, s_frames)
    yaw_path = np.unwrap(geo.headings_rad(path))
    yaw = np.interp(s_frames, s, yaw_path)
    speed = np.gradient(s_frames, timestamps) if len(timestamps) > 1 else np.zeros(len(timestamps))
    poses = np.column_stack([xy, np.angle(np.exp(1j * yaw))])
    return Drive(np.round(timestamps, 3), poses, speed)
