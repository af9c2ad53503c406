"""Algorithm 1, Step 3: intra-trip temporal consistency (Eq. 8).

One trip instance (a spliced element) appears in several consecutive sub-maps of its trip;
against another trip it must match the same instance every time. For each trip pair and each
instance ``k`` the votes of all sub-map pairs are pooled,
``k' = argmax_k' sum_n x_kn c_kn / sum_n x_kn c_kn`` (Eq. 8), in both directions; a match that
disagrees with the vote is corrected to the voted instance when that instance is in the
sub-map (and free), dropped otherwise, and the pair is registered again (GNC) with the
corrected matches, starting from its previous pose.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from typing import cast

from csr_core.alignment.association import PairMatch, match_pair
from csr_core.alignment.params import AlignmentParams, NoiseScales
from csr_core.alignment.submaps import Circle, Submap


def vote_instances(pairs: Sequence[PairMatch]) -> tuple[dict, dict]:
    """Eq. 8 votes for one trip pair: ``best_j[a] = b`` and ``best_i[b] = a``."""
    fwd: dict[int, dict[int, float]] = defaultdict(lambda: defaultdict(float))
    bwd: dict[int, dict[int, float]] = defaultdict(lambda: defaultdict(float))
    for p in pairs:
        for (a, b), c in zip(p.instance_matches, p.match_confidences, strict=False):
            fwd[a][b] += float(c)
            bwd[b][a] += float(c)
    best_j = {a: max(v, key=cast(Callable[[int], float], v.get)) for a, v in fwd.items()}
    best_i = {b: max(v, key=cast(Callable[[int], float], v.get)) for b, v in bwd.items()}
    return best_j, best_i


def temporal_consistency(
    matched: Sequence[PairMatch],
    submaps: Sequence[Submap],
    circles: Sequence[Circle],
    noise: NoiseScales,
    params: AlignmentParams,
) -> list[PairMatch]:
    groups: dict[tuple[int, int], list[PairMatch]] = defaultdict(list)
    for p in matched:
        groups[(p.trip_i, p.trip_j)].append(p)
    out: list[PairMatch] = []
    for group in groups.values():
        best_j, best_i = vote_instances(group)
        for p in group:
            si, sj = submaps[p.i], submaps[p.j]
            j_of_instance = {e.instance_index: n for n, e in enumerate(sj.elements)}
            i_of_instance = {e.instance_index: n for n, e in enumerate(si.elements)}
            new, used, changed = [], set(), False
            for (k, kp), (a, b) in zip(p.element_matches, p.instance_matches, strict=False):
                b_hat, a_hat = best_j.get(a), best_i.get(b)
                # a disagreement counts only when the voted partner is in this sub-map too
                # (a trip may splice one line into several instances along the road)
                wrong_j = b_hat != b and b_hat in j_of_instance
                wrong_i = a_hat != a and a_hat in i_of_instance
                if not (wrong_j or wrong_i):
                    new.append((k, kp))
                    used.add(kp)
                    continue
                changed = True
                kp_hat = j_of_instance.get(cast(int, b_hat)) if wrong_j else None
                if (
                    kp_hat is not None
                    and kp_hat not in used
                    and best_i.get(b_hat) == a
                    and si.elements[k].type == sj.elements[kp_hat].type
                ):
                    new.append((k, kp_hat))
                    used.add(kp_hat)
            if not changed:
                out.append(p)
                continue
            redo = match_pair(
                si,
                sj,
                circles[p.circle_id],
                noise,
                params,
                forced_matches=new,
                initial_xyyaw=p.delta_local_xyyaw,
            )
            if redo is not None:
                out.append(redo)
    return out
