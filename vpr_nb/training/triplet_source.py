"""The triplet batch source: NetVLAD-style weakly supervised triplets mined on a split, with a triplet-family loss.

:class:`TripletSource` follows NetVLAD (Arandjelović et al., CVPR 2016, Sec. 4): at the start of every epoch
(and every ``cache_refresh`` queries) the descriptors of the training images are recomputed; each query gets
its best potential positive (within the training radius; or, with ``positive="random"``, one drawn at random)
and its M hardest negatives (beyond the evaluation radius) from :func:`vpr_nb.mining.mine_triplets`; the loss
is a :class:`vpr_nb.losses.TripletFamilyLoss` object, one of DW-T-Loss's Eqs. (3), (4)x(3), (5)-(8), (9). The
source builds batches; the loss object it is given holds the loss's parameters (margin, sigma, eps, ...).
"""
from __future__ import annotations

import numpy as np
import torch

from .. import losses as L
from .._checks import check_int, check_positive, validated_inputs
from ..evaluation import compute_descriptors
from ..image_tensors import images_to_tensor
from ..mining import check_positive_rule, mine_triplets
from ..split import check_split
from .device import unwrap_ddp
from .divergence import NotFinite


def _positive_seed(rng: np.random.Generator) -> np.random.SeedSequence:
    """A child of ``rng``'s SeedSequence (no draw from ``rng``): the seed of an epoch's random positives."""
    ss = getattr(rng.bit_generator, "seed_seq", None)
    if not isinstance(ss, np.random.SeedSequence):
        raise ValueError("positive='random' seeds its draws from the step rng's SeedSequence: pass a generator made "
                         "by np.random.default_rng(seed), e.g. default_rng([seed, epoch])")
    return ss.spawn(1)[0]


class TripletSource:
    """NetVLAD triplets on a split: anchors are the split's queries (optionally also its database).

    Args:
        split: a :class:`vpr_nb.split.Split` with queries (headings if ``max_heading_diff`` is set);
            potential positives are ``split.positives(train_pos_radius)`` and the images never used as
            negatives ``split.positives(neg_radius)``, both inside each region (city) of the split.
        loss: a :class:`vpr_nb.losses.TripletFamilyLoss` object holding its parameters:
            ``TripletLoss(margin)`` (Eq. 3), ``WeightedTripletLoss(margin, sigma, eps)`` (Eq. 4 x Eq. 3),
            ``CETripletLoss()`` (Eqs. 5-8), ``DWTripletLoss(sigma, eps)`` (Eq. 9). Default: Eq. (3) with
            the paper's margin.
        batch_size: queries per optimiser step; num_negatives: M; num_candidates: random negatives
            sampled per query; cache_refresh: recompute the descriptor cache every this many queries
            (None: once per epoch). pytorch-NetVlad uses M=10, 1000 candidates and a refresh every
            1000 of Pittsburgh30k's 7416 training queries; the defaults here (M=5, 300 candidates,
            once per epoch = every ~580 queries of the tiny city) scale that to the tiny world.
        max_heading_diff: keep only positives facing the query's way (see ``mine_triplets``).
        neg_radius: negatives lie beyond this many metres (default: the split's evaluation radius,
            NetVLAD's 25 m, or its ``train_pos_radius`` when that is larger, so that positives may lie beyond
            the evaluation radius -- notebook 03's positive control -- and negatives still beyond them). On a densely sampled route (positives = +-1 frame) a larger radius keeps
            near-duplicates of the positive out of the negatives.
        positive: ``"best"`` (default: NetVLAD's best potential positive, nearest in descriptor space) or
            ``"random"``: one potential positive drawn uniformly at random, from a generator seeded by the
            step's ``rng`` (its ``SeedSequence``, i.e. ``(seed, epoch)`` in :func:`vpr_nb.training.train`) and
            the query index, without drawing from ``rng``: the draw depends neither on the model nor on the
            batch order, runs with the same seed get the same positives, and the negatives' draws are the best
            rule's. DW-T-Loss's Eq. (4) ranks positives by distance, which the best rule keeps nearly constant.
    The per-step loss is the loss summed over the step's triplets divided by the number of queries.
    """

    def __init__(self, split, loss: L.TripletFamilyLoss = L.TripletLoss(), *, batch_size: int = 16,
                 num_negatives: int = 5, num_candidates: int = 300, cache_refresh: int | None = None,
                 max_heading_diff: float | None = None, neg_radius: float | None = None, positive: str = "best"):
        if not isinstance(loss, L.TripletFamilyLoss):
            raise ValueError(f"loss must be a triplet-family loss object (vpr_nb.losses.TripletLoss(margin), "
                             f"WeightedTripletLoss(margin, sigma, eps), CETripletLoss(), DWTripletLoss(sigma, eps)), "
                             f"got {loss!r}")
        check_split(split, "the training split")
        if not split.has_queries or len(split.db_utm) == 0:
            raise ValueError(f"the training split {split.name} has no queries or no database images: triplets "
                             "need both (train on places instead)")
        self.split, self.loss = split, loss
        self.batch_size = check_int(batch_size, "batch_size")
        self.num_negatives = check_int(num_negatives, "num_negatives")
        self.num_candidates = check_int(num_candidates, "num_candidates")
        self.cache_refresh = None if cache_refresh is None else check_int(cache_refresh, "cache_refresh")
        self.max_heading_diff = max_heading_diff
        self.positive = check_positive_rule(positive)
        self.neg_radius = (max(split.pos_radius, split.train_pos_radius) if neg_radius is None
                           else check_positive(neg_radius, "neg_radius"))
        self.q, self.db = split.q_images, split.db_images
        self.positives = split.positives(split.train_pos_radius)   # per query, inside its region
        self.near = split.positives(self.neg_radius)
        self.neg_cache: dict[int, np.ndarray] = {}

    def state_dict(self) -> dict:
        keys = sorted(self.neg_cache)
        vals = np.stack([self.neg_cache[k] for k in keys]) if keys else np.zeros((0, self.num_negatives), np.int64)
        return {"keys": torch.as_tensor(np.asarray(keys, np.int64)), "values": torch.as_tensor(vals)}

    def load_state_dict(self, state: dict) -> None:
        self.neg_cache = {int(k): v.numpy() for k, v in zip(state["keys"], state["values"])}

    def _descriptors(self, model):
        model = unwrap_ddp(model)
        q, db = compute_descriptors(model, self.split.q_images), compute_descriptors(model, self.split.db_images)
        if not (np.isfinite(q).all() and np.isfinite(db).all()):
            raise NotFinite("descriptors of the training images")
        return q, db

    def untrainable(self) -> dict[str, int]:
        """Training queries that can never give a triplet, by reason, from the data alone: ``no_positive``
        (none within ``split.train_pos_radius``), ``heading`` (positives, none facing within
        ``max_heading_diff``), ``negatives`` (fewer than M database images beyond ``neg_radius``); and
        ``trainable``, the rest, out of ``queries``."""
        if getattr(self, "_untrainable", None) is None:
            n_db, no_pos, heading, few = len(self.db), 0, 0, 0
            s, h = self.split, self.max_heading_diff
            qh, dh = (None, None) if h is None or s.q_heading is None or s.db_heading is None else \
                (np.asarray(s.q_heading, dtype=np.float64), np.asarray(s.db_heading, dtype=np.float64))
            for i, (pos, near) in enumerate(zip(self.positives, self.near)):
                if len(pos) == 0:
                    no_pos += 1
                elif qh is not None and not (np.abs((dh[pos] - qh[i] + 180.0) % 360.0 - 180.0) <= h).any():
                    heading += 1
                elif n_db - len(near) < self.num_negatives:
                    few += 1
            q = len(self.positives)
            self._untrainable = {"queries": q, "no_positive": no_pos, "heading": heading, "negatives": few,
                                 "trainable": q - no_pos - heading - few}
        return self._untrainable

    def no_step_reason(self) -> str:
        """Why an epoch formed no triplet (for :func:`train_epoch`'s error)."""
        u, s = self.untrainable(), self.split
        parts = [f"no positives within {s.train_pos_radius:g} m for {u['no_positive']} of {u['queries']} "
                 f"training queries"]
        fixes = ["check the query and database positions or use a larger training radius (the split's "
                 "train_pos_radius)"] if u["no_positive"] else []
        if u["heading"]:
            parts.append(f"no positive facing within {self.max_heading_diff:g} degrees for {u['heading']} more")
            fixes.append("allow more heading difference (source.max_heading_diff)")
        if u["negatives"]:
            parts.append(f"fewer than {self.num_negatives} database images beyond {self.neg_radius:g} m (negatives) "
                         f"for {u['negatives']} more")
            fixes.append("use fewer negatives (source.num_negatives)")
        return "; ".join(parts) + f" (training split {s.name})" + (": " + ", or ".join(fixes) if fixes else "")

    def _collapsed_loss(self, b: int, m: int, dim: int, geo) -> float:
        """The loss of this step's triplets if every descriptor were the same unit vector."""
        e = torch.zeros(b, dim, dtype=geo.dtype)
        e[:, 0] = 1.0
        return float(self.loss(e, e, e.unsqueeze(1).expand(b, m, dim), geo.cpu()))

    def steps(self, model, rng: np.random.Generator, shard: tuple[int, int] = (0, 1), device=None):
        """Yield one loss tensor per optimiser step of an epoch.

        With ``shard=(rank, world)`` (distributed training) every process mines the whole batch
        (same random draws, same negative cache) and computes the loss of its share of the
        triplets, scaled so that the average over processes equals the single-process loss.
        """
        rank, world = shard
        s = self.split
        if self.untrainable()["trainable"] == 0:
            return                                 # no query can give a triplet: train_epoch says why
        heading = {}
        if self.max_heading_diff is not None:
            heading = dict(q_heading=s.q_heading, db_heading=s.db_heading, max_heading_diff=self.max_heading_diff)
        pick = {}
        if self.positive != "best":
            pick = dict(positive=self.positive, positive_seed=_positive_seed(rng))
        order = rng.permutation(len(self.q))
        refresh = self.cache_refresh or len(order)
        for start in range(0, len(order), self.batch_size):
            if start == 0 or start // refresh != (start - self.batch_size) // refresh:  # refresh point crossed
                q_desc, db_desc = self._descriptors(model)
            ids = order[start:start + self.batch_size]
            with validated_inputs():        # the descriptors were checked finite when computed (_descriptors)
                tb = mine_triplets(q_desc, db_desc, s.q_utm, s.db_utm, ids, train_pos_radius=s.train_pos_radius,
                                   neg_radius=self.neg_radius, num_negatives=self.num_negatives,
                                   num_candidates=min(self.num_candidates, len(self.db)),
                                   neg_cache=self.neg_cache, rng=rng, positives=[self.positives[i] for i in ids],
                                   near=[self.near[i] for i in ids], **heading, **pick)
            v = np.flatnonzero(tb.valid)
            total = len(v)
            if total < world:
                continue                       # every process skips the same steps
            v = v[rank::world]
            b, m = len(v), self.num_negatives
            x = images_to_tensor(np.concatenate([self.q[tb.query[v]], self.db[tb.positive[v]],
                                                 self.db[tb.negatives[v].reshape(-1)]])).to(device)
            out = model(x).float()
            if not torch.isfinite(out).all():
                raise NotFinite("descriptors")
            q, p, n = out[:b], out[b:2 * b], out[2 * b:].view(b, m, -1)
            geo = torch.as_tensor(tb.geo_qp[v], dtype=out.dtype, device=out.device)
            self.last_collapsed_loss = self._collapsed_loss(b, m, out.shape[1], geo) * (world / total)
            yield self.loss(q, p, n, geo) * (world / total)
