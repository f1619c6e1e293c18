"""Top-k order: whether the top-k retrievals of each query are sorted by geographic distance.

For a query's retrievals in rank order, a pair ``(a, b)`` with ``a`` ranked before ``b`` is correctly
ordered when ``geo(a) <= geo(b)``; :func:`topk_order_agreement` reports the fraction of correctly ordered
pairs and Kendall's tau-b between rank and geographic distance for every query, :func:`query_topk` the
top-k of one query (the notebook's query explorer).
"""
from __future__ import annotations

from dataclasses import dataclass

import faiss
import numpy as np

from .._checks import check_geo_descriptors, check_int, check_positive
from .._threads import single_threaded_call
from .pairs import _CHUNK_FLOATS


@dataclass(frozen=True, eq=False)
class OrderAgreement:
    """How well the top-k retrievals of each query are sorted by geographic distance.

    Attributes:
        topk: ``(Q, k)`` database indices retrieved per query, best first.
        topk_geo: ``(Q, k)`` geographic distance (m) from the query to each retrieval.
        fraction_correct: ``(Q,)`` fraction of retrieval pairs ``(a, b)``, ``a`` ranked before
            ``b``, with ``geo(a) <= geo(b)``.
        kendall_tau: ``(Q,)`` Kendall tau-b between rank and geographic distance (NaN when all
            k retrievals are at the same distance).
        mean_fraction_correct: mean of ``fraction_correct``.
        mean_kendall_tau: mean of ``kendall_tau`` over queries where it is defined.
    """

    topk: np.ndarray
    topk_geo: np.ndarray
    fraction_correct: np.ndarray
    kendall_tau: np.ndarray
    mean_fraction_correct: float
    mean_kendall_tau: float


def _order_stats(geo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``(Q, k)`` geo distances in rank order: fraction of correct pairs and tau-b."""
    iu, ju = np.triu_indices(geo.shape[1], 1)  # pairs (a, b) with a ranked before b
    n0 = len(iu)
    concordant = np.empty(len(geo), dtype=np.int64)
    discordant = np.empty(len(geo), dtype=np.int64)
    chunk = max(1, _CHUNK_FLOATS // n0)
    for s in range(0, len(geo), chunk):
        sign = np.sign(geo[s:s + chunk, ju] - geo[s:s + chunk, iu])
        concordant[s:s + chunk] = (sign > 0).sum(axis=1)
        discordant[s:s + chunk] = (sign < 0).sum(axis=1)
    ties = n0 - concordant - discordant
    fraction = (concordant + ties) / n0
    with np.errstate(invalid="ignore", divide="ignore"):
        tau = (concordant - discordant) / np.sqrt(n0 * (n0 - ties).astype(np.float64))
    return fraction, tau


@single_threaded_call
def topk_order_agreement(q_desc, db_desc, q_utm, db_utm, k: int = 10) -> OrderAgreement:
    """Are the top-k retrievals of each query sorted by geographic distance?

    Retrieves the ``k`` nearest database descriptors of every query (exact L2 search,
    ``faiss.IndexFlatL2``). For each query, a pair of retrievals ``(a, b)`` with ``a`` ranked
    before ``b`` is *correctly ordered* when ``geo(a) <= geo(b)``. Reports the fraction of
    correctly ordered pairs and Kendall's tau-b between the retrieval rank and the geographic
    distance (+1: perfectly sorted by distance, -1: reversed). This is the top-k sorting that
    CliqueMining ties to the Geographic Distance Sensitivity.
    """
    qd, dbd, qu, du = check_geo_descriptors(q_desc, db_desc, q_utm, db_utm)
    k = check_int(k, "k", minimum=2, maximum=len(dbd))
    index = faiss.IndexFlatL2(dbd.shape[1])
    index.add(dbd)
    _, topk = index.search(qd, k)
    topk = topk.astype(np.int64)
    geo = np.sqrt(((du[topk] - qu[:, None, :]) ** 2).sum(axis=2))
    fraction, tau = _order_stats(geo)
    finite = np.isfinite(tau)
    return OrderAgreement(topk=topk, topk_geo=geo, fraction_correct=fraction, kendall_tau=tau,
                          mean_fraction_correct=float(fraction.mean()),
                          mean_kendall_tau=float(tau[finite].mean()) if finite.any() else float("nan"))


@dataclass(frozen=True, eq=False)
class QueryTopK:
    """The top-k retrievals of one query with their true geographic distances.

    Attributes:
        query: the query index.
        db_index: ``(k,)`` database indices, nearest descriptor first.
        desc_distance: ``(k,)`` Euclidean descriptor distances.
        geo_distance: ``(k,)`` geographic distances (m) from the query.
        is_positive: ``(k,)`` True where ``geo_distance <= pos_radius`` (all False without a radius).
        fraction_correct: fraction of retrieval pairs ``(a, b)``, ``a`` ranked before ``b``, with
            ``geo(a) <= geo(b)`` (as in :func:`topk_order_agreement`).
    """

    query: int
    db_index: np.ndarray
    desc_distance: np.ndarray
    geo_distance: np.ndarray
    is_positive: np.ndarray
    fraction_correct: float

    def table(self) -> str:
        """The retrievals as a fixed-width text table (rank, db index, descriptor and geographic distance)."""
        lines = [f"query {self.query}: {self.fraction_correct:.3f} of the top-{len(self.db_index)} pairs sorted by distance",
                 "rank  db index  desc dist  geo dist (m)  positive"]
        for r, (i, dd, g, p) in enumerate(zip(self.db_index, self.desc_distance, self.geo_distance, self.is_positive)):
            lines.append(f"{r + 1:>4}  {i:>8}  {dd:>9.3f}  {g:>12.1f}  {'yes' if p else 'no':>8}")
        return "\n".join(lines)


def query_topk(q_desc, db_desc, q_utm, db_utm, query: int, k: int = 5, pos_radius: float | None = None) -> QueryTopK:
    """Top-k database images of query ``query`` by descriptor distance, with their geographic distances.

    The pure function behind the notebook's query-picker widget: exact Euclidean search (ties
    broken by database index), then the true distance of every retrieval and whether the top-k is
    sorted by it (CliqueMining's "close, but not there": the nearest image should come first).
    """
    qd, dbd, qu, du = check_geo_descriptors(q_desc, db_desc, q_utm, db_utm)
    query = check_int(query, "query", minimum=0, maximum=len(qd) - 1)
    k = check_int(k, "k", minimum=1, maximum=len(dbd))
    if pos_radius is not None:
        pos_radius = check_positive(pos_radius, "pos_radius")
    diff = dbd.astype(np.float64) - qd[query].astype(np.float64)
    desc = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    top = np.argsort(desc, kind="stable")[:k]
    geo = np.sqrt(((du[top] - qu[query]) ** 2).sum(axis=1))
    if k >= 2:
        fraction = float(_order_stats(geo[None])[0][0])
    else:
        fraction = 1.0
    pos = np.zeros(k, dtype=bool) if pos_radius is None else geo <= pos_radius
    return QueryTopK(query=query, db_index=top.astype(np.int64), desc_distance=desc[top], geo_distance=geo,
                     is_positive=pos, fraction_correct=fraction)
