"""The diagnosis that the live supervisor node and offline ``fdi-ros diagnose`` share.

One step per feature vector: the residuals of the on-line bank models go in; out come the
symptoms of the reference model's residuals (thresholds -> ++/+/o/-, debounced), the candidate
faults of the fault-symptom table, and the expert supervisor's minimum-residual index I*, fault
index F* (held for T0) and bank switch. Live and offline runs call exactly this code, so a bag
replayed through the graph and the same bag diagnosed offline give the same answer.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from fdi_ros.core.fst import (
    FaultSymptomTable,
    covering,
    isolate,
    isolate_in_sign,
    load_fault_symptom_tables,
)
from fdi_ros.core.graphconfig import GraphConfig
from fdi_ros.core.residual_models import ResidualModel, load_residual_model
from fdi_ros.core.supervisor import ExpertSupervisor, fault_type
from fdi_ros.core.symptoms import (
    SymptomConfig,
    SymptomGenerator,
    SymptomState,
    load_thresholds,
    symptom_name,
)
from fdi_ros.core.types import Diagnosis, FeatureVector, ResidualVector


@dataclass(frozen=True)
class Step:
    """Result of one diagnosis step."""

    diagnosis: Diagnosis
    symptoms: SymptomState | None  # of the reference model (None: no symptom stage)
    switched: bool  # the set of on-line models changed at this step
    added: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()


def _make_symptom_stage(cfg: GraphConfig
                        ) -> tuple[SymptomGenerator | None, FaultSymptomTable | None, str]:
    """(SymptomGenerator, fault-symptom table or None, reference model id) from the config."""
    if not cfg.symptoms:
        return None, None, ""
    s = cfg.symptoms
    conf = s.get("config")
    if isinstance(conf, str):
        conf = load_thresholds(cfg.resolve(conf))
    elif isinstance(conf, dict):
        conf = SymptomConfig.from_dict(conf)
    else:
        raise ValueError(f"{cfg.path}: symptoms.config must be a mapping or a file")
    table = None
    if s.get("table"):
        tables = load_fault_symptom_tables(cfg.resolve(s["table"]))
        key = s.get("table_key", next(iter(tables)))
        if key not in tables:
            raise ValueError(f"{cfg.path}: no table {key!r} in {s['table']} ({list(tables)})")
        table = tables[key]
    return SymptomGenerator(conf), table, str(s.get("model", "nominal"))


# Default share of the runner-up hypothesis' norm the best one must stay below to isolate
# (graph configuration: ``symptoms.ambiguity``; 1 = the paper's plain minimum)
AMBIGUITY = 0.7


class Diagnoser:
    """Symptoms + fault-symptom table + expert supervisor over a model bank (pure core).

    Parameters
    ----------
    cfg : the graph configuration (bank, T0, symptom settings).
    """

    def __init__(self, cfg: GraphConfig) -> None:
        self.cfg = cfg
        self.supervisor = ExpertSupervisor(bank=cfg.bank_models, t0_s=cfg.t0_s,
                                           stale_s=cfg.stale_s)
        self.symptom_gen, self.table, self.reference_id = _make_symptom_stage(cfg)
        self.detection_time = math.nan
        sym = cfg.symptoms or {}
        self.max_mismatch = int(sym.get("max_mismatch", 1))
        self.explain_norm = float(sym.get("explain_norm", math.inf))
        # the best hypothesis isolates only with a norm below this share of the runner-up's
        self.ambiguity = float(sym.get("ambiguity", AMBIGUITY))
        # regimes where the table's signatures (measured elsewhere) do not hold: there every
        # fault is a candidate and the bank's hypotheses, identified in the regime, decide
        regimes = sym.get("hypothesis_regimes", [])
        if not isinstance(regimes, list) or not all(isinstance(r, str) for r in regimes):
            raise ValueError(f"{cfg.path}: symptoms.hypothesis_regimes must be a list of "
                             "regime names")
        self.hypothesis_regimes = frozenset(regimes)
        self._candidates: dict[tuple[int, ...], tuple[tuple[str, ...], tuple[str, ...]]] = {}
        self._fault_types = {m.id: m.fault_types for m in self.supervisor.bank}
        self._partial: dict[tuple[Any, ...], tuple[str, ...]] = {}

    @property
    def models_online(self) -> tuple[str, ...]:
        """Models whose residuals are needed now: the supervisor's on-line set plus the
        reference model whose residuals give the symptoms (it never goes off line)."""
        online = self.supervisor.models_online
        if self.reference_id and self.reference_id not in online:
            return (self.reference_id, *online)
        return online

    def symptoms_of(self, ref: ResidualVector) -> SymptomState | None:
        """Symptoms of the reference model's residuals (stateful: call once per index, in
        order). The live node calls this as soon as the reference residual arrives, so the
        symptom is published without waiting for the rest of the bank."""
        return self.symptom_gen.update(ref) if self.symptom_gen is not None else None

    def _partial_candidates(self, symptoms: SymptomState) -> tuple[str, ...]:
        """The fault a regime that judges some residuals only can isolate: the signatures
        compared on the judged symptoms, in sign (the table's intensities hold where it was
        measured), and a candidate only if exactly one fault type matches: with fewer
        symptoms several faults look alike, and the bank's hypotheses, fitted to one or two
        residuals, would then compete on noise (detected there, no isolation)."""
        if self.symptom_gen is None or self.table is None:
            return ()
        cfg = self.symptom_gen.config
        names = tuple(symptom_name(r) for r, j in zip(cfg.names, cfg.judged(symptoms.regime))
                      if j)
        by_name = symptoms.by_name()
        key = (symptoms.regime, *(int(np.sign(by_name.get(k, 0))) for k in names))
        hit = self._partial.get(key)
        if hit is None:
            match = isolate_in_sign(by_name, self.table, names)
            hit = self._partial[key] = tuple(match) if len(
                {fault_type(f) for f in match}) == 1 else ()
        return hit

    def update(self, index: int, t: float, residuals: Mapping[str, ResidualVector], *,
               symptoms: SymptomState | None = None) -> Step:
        """One step. ``symptoms``: the result of :meth:`symptoms_of` for this index when the
        caller computed it already (otherwise it is computed here from ``residuals``)."""
        before = self.models_online
        candidates: tuple[str, ...] = ()
        # the candidates the table's signatures name (the rest compete on their hypotheses'
        # evidence alone: rows merely covering the symptoms, or a hypothesis regime)
        backed: tuple[str, ...] = ()
        feed: dict[str, ResidualVector] = dict(residuals)
        not_isolable = ambiguous = unexplained = False
        if self.symptom_gen is not None:
            ref = residuals.get(self.reference_id)
            if symptoms is None and ref is not None:
                symptoms = self.symptoms_of(ref)
            if (ref is None or not ref.valid) and not self.supervisor.isolated:
                # Without valid reference residuals nothing can be said at this step: the
                # hypotheses never compete without the reference model (e.g. while it is away
                # or restarting after an external lifecycle change).
                feed = {}
            active = symptoms is not None and symptoms.valid and any(symptoms.levels)
            if symptoms is not None and active and self.table is not None and \
                    symptoms.regime in self.hypothesis_regimes:
                candidates = tuple(self.table)
            elif symptoms is not None and active and self.table is not None and \
                    not self.symptom_gen.config.judges_all(symptoms.regime):
                candidates = backed = self._partial_candidates(symptoms)
            elif symptoms is not None and active and self.table is not None:
                cols = self.table.columns
                observed = symptoms.in_order(cols) if cols else tuple(symptoms.levels)
                # The faults the symptoms do not contradict: a fault outside this list
                # cannot explain the residuals, however small its model's residual.
                cached = self._candidates.get(observed)
                if cached is None:   # a pure function of the pattern: once per pattern
                    matched = tuple(isolate(observed, self.table,
                                            max_mismatch=self.max_mismatch,
                                            opposite="exclude", keep="all"))
                    cached = self._candidates[observed] = (tuple(dict.fromkeys(
                        (*matched, *covering(observed, self.table)))), matched)
                candidates, backed = cached
            if not self.supervisor.isolated:
                if not active:
                    # No symptom: the reference model explains the data by definition; the
                    # hypotheses do not compete (the parity equations detect, the bank
                    # isolates).
                    if ref is not None and ref.valid:
                        feed[self.reference_id] = replace(ref, norm=0.0)
                elif self.table is not None:
                    # Only a hypothesis that explains the residuals may be isolated: its fault
                    # consistent with the fault-symptom table and its own residual within
                    # ``explain_norm``; never the least bad of the rest (no elimination).
                    keep = {m.id for m in self.supervisor.bank
                            if not m.faults or m.fault_types & set(candidates)}
                    feed = {k: v for k, v in feed.items() if k in keep and (
                        k == self.reference_id or not v.norm > self.explain_norm)}
                    not_isolable = not any(k != self.reference_id and v.valid
                                           for k, v in feed.items())
                    by_norm = sorted((v.norm, k) for k, v in feed.items()
                                     if k != self.reference_id and v.valid)
                    ranked = [norm for norm, _ in by_norm]
                    ref_v = feed.get(self.reference_id)
                    if len(ranked) >= 2 and not ranked[0] < self.ambiguity * ranked[1]:
                        # two hypotheses explain the residuals about as well: no isolation
                        # by a small difference (detected, ambiguous), the hold time restarts
                        feed = {k: v for k, v in feed.items() if k == self.reference_id}
                        ambiguous = True
                    elif ranked and ref_v is not None and ref_v.valid \
                            and math.isfinite(ref_v.norm) \
                            and not ranked[0] < self.ambiguity * ref_v.norm \
                            and not any(self._fault_types[k] & set(backed)
                                        for norm, k in by_norm if norm == ranked[0]):
                        # a candidate the table does not name, explaining the residuals
                        # hardly better than the nominal model: the least bad, not an
                        # explanation (the true fault may be one the table excludes here,
                        # its row measured at another operating point): detected, not
                        # isolated
                        feed = {k: v for k, v in feed.items() if k == self.reference_id}
                        unexplained = True
        fm = feed.get(self.supervisor.fault_model)
        if fm is None or not fm.valid:
            # The model believed to match the plant (nominal at start) is the baseline of the
            # comparison: without it a change of I* would be isolation by elimination.
            feed = {}
        d = self.supervisor.update(t, feed)
        if symptoms is not None and symptoms.valid and any(symptoms.levels) \
                and math.isnan(self.detection_time):
            self.detection_time = t  # a symptom is a detection (the parity-equation path)
        if not math.isnan(d.detection_time) and math.isnan(self.detection_time):
            self.detection_time = d.detection_time
        state = d.state
        if state == "not_valid" and self.supervisor.isolated:
            state = "isolated"  # a step without valid residuals does not undo an isolation
        if symptoms is not None and not symptoms.valid and state == "no_fault":
            state = "not_valid"
        if symptoms is not None and symptoms.valid and not any(symptoms.levels) \
                and state == "not_valid":
            # the parity equations judged the segment and found nothing: fault-free, whether
            # or not enough hypotheses were valid to compete (they isolate, they do not
            # detect; e.g. with the EGR valve open, where the hypotheses' maps do not hold)
            state = "no_fault"
        if symptoms is not None and symptoms.valid and any(symptoms.levels) \
                and state in ("no_fault", "not_valid"):
            state = "detected"
        extra = dict(d.extra)
        if ambiguous and state == "detected":
            extra["ambiguous"] = True
        if unexplained and state == "detected":
            extra["unexplained"] = True
        if not_isolable and state == "detected":
            # "detected, not isolable with the models on line": name the table's candidates,
            # those whose models are away (off line, dead, stale) included
            extra["not_isolable"] = True
            online = self.supervisor.models_online
            extra["away"] = tuple(m.id for m in self.supervisor.bank
                                  if m.id in online and m.fault_types & set(candidates)
                                  and (m.id not in residuals or not residuals[m.id].valid))
        d = replace(d, index=int(index), state=state,
                    candidate_faults=candidates or d.candidate_faults,
                    models_online=self.models_online, detection_time=self.detection_time,
                    extra=extra)
        after = self.models_online
        added = tuple(m for m in after if m not in before)
        removed = tuple(m for m in before if m not in after)
        return Step(d, symptoms, bool(added or removed), added, removed)


def diagnose_offline(cfg: GraphConfig, features: Iterable[FeatureVector], *,
                     models: Mapping[str, ResidualModel] | None = None, progress: bool = False,
                     batch: bool = True
                     ) -> list[tuple[FeatureVector, dict[str, ResidualVector], Step]]:
    """Run the whole bank and the diagnoser over feature vectors (no ROS, many x real time).

    Only the models on line at each step are evaluated, as in the live graph; a model taken on
    line after an isolation is reset first, as the live residual node is on activation.
    ``batch``: models that offer ``batch(features, shared)`` compute the stream run by run
    with array operations (same results); ``batch=False`` asks every model segment by
    segment, as the live graph does (the reference path of the tests).
    """
    if models is None:
        models = {e.id: load_residual_model(cfg.resolve_spec(e.model), model_id=e.id)
                  for e in cfg.bank}
    diag = Diagnoser(cfg)
    out = []
    feats = list(features)
    ref_id = diag.reference_id if diag.symptom_gen is not None else ""
    ref_rvs: list[ResidualVector] = []
    symptoms: list[SymptomState] = []
    if batch:
        shared: dict[str, object] = {}
        wrapped: dict[str, ResidualModel] = {}
        for mid, m in models.items():
            hook = getattr(m, "batch", None)
            wrapped[mid] = hook(feats, shared) if callable(hook) else m
        models = wrapped
        gen = diag.symptom_gen
        if ref_id in models and gen is not None:
            # The reference model is always on line (never reset): its residuals and the
            # symptoms of the whole stream first, the bank and the supervisor step by step.
            ref_rvs = [models[ref_id].residuals(fv) for fv in feats]
            symptoms = gen.run(ref_rvs)
    it: Iterable[FeatureVector] = feats
    if progress:
        from tqdm import tqdm

        it = tqdm(feats, desc="diagnose", unit="seg")
    for k, fv in enumerate(it):
        if symptoms:
            res = {mid: ref_rvs[k] if mid == ref_id else models[mid].residuals(fv)
                   for mid in diag.models_online}
            step = diag.update(fv.index, fv.t_end, res, symptoms=symptoms[k])
        else:
            res = {mid: models[mid].residuals(fv) for mid in diag.models_online}
            step = diag.update(fv.index, fv.t_end, res)
        for mid in step.added:
            if symptoms and mid == ref_id:
                raise RuntimeError("the reference model went off line in an offline run")
            reset = getattr(models[mid], "reset", None)
            if callable(reset):
                reset()
        out.append((fv, res, step))
    return out

