"""Expert supervisor of a bank of models: minimum-residual detection, hold-time isolation.

Pure core (no rclpy), shared by ``fdi-ros reproduce turbofan``, offline ``fdi-ros diagnose``
and the live ROS supervisor node. It implements section 3.2 of Diao & Passino (2004):

* the **model bank determinator** :func:`models_online` (which models run, given the faults
  isolated so far);
* the **minimum-residual index** (paper eq. 17)

  .. math:: I^*(k) = \\arg\\min_{i \\in S} |r_i(k)|

  over the on-line set S; a change of I* away from the current fault model is a *detection*;
* the **fault index** (paper eq. 18)

  .. math:: F^*(k) = i \\quad\\text{if}\\quad I^*(j) = i \\;\\forall\\, j:\\; k - T_0 \\le j \\le k

  i.e. a fault situation is *isolated* only when the same model has had the minimum residual
  without interruption for at least ``T0`` seconds; this hold time buys robustness against
  transients in which a wrong model is briefly best.

Model identifiers and fault ids
-------------------------------
A bank model is a :class:`BankModel` ``(id, faults)``; ``faults`` is a frozenset of *fault ids*
of the form ``"<type>_<size>"`` (``"fan_small"``, ``"hub_large"``) or a bare ``"<type>"`` when a
fault kind has no sizes. The empty set is the fault-free (nominal) model. The *type* of a fault
id is the part before the last underscore when the rest is a known size word (``small``,
``medium``, ``large``), else the whole id.

Bank rules (generalising the paper's three rules)
-------------------------------------------------
Let T be the set of fault *types* isolated so far (empty at start). On line are the models whose
fault types U satisfy ``T <= U`` and ``len(U) <= len(T) + 1``:

* nothing isolated -> the nominal model and every single-fault model;
* fault i isolated -> all models of fault type i alone **in every size** (so a fault that grows,
  small -> large, is followed, as in the paper's Fig. 6 where the three hub models stay on line)
  plus every double-fault model containing type i (any sizes);
* two types isolated -> the double models of those two types in every size plus the triple
  models containing both; and so on.

Sizes are not monotone constraints: a smaller size of an isolated fault type stays on line, so
a first isolation that picked too large a size can still be corrected.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from fdi_ros.core.types import Diagnosis, ResidualVector

SIZE_WORDS = ("small", "medium", "large")


def fault_type(fault_id: str) -> str:
    """Fault type of a fault id: ``"fan_small" -> "fan"``, ``"leak" -> "leak"``."""
    head, sep, tail = fault_id.rpartition("_")
    return head if sep and tail in SIZE_WORDS and head else fault_id


@dataclass(frozen=True)
class BankModel:
    """One model of the bank: an id and the set of fault ids it represents (empty = nominal)."""

    id: str
    faults: frozenset[str] = frozenset()

    def __post_init__(self) -> None:
        if not self.id:
            raise ValueError("a bank model needs a non-empty id")
        object.__setattr__(self, "faults", frozenset(self.faults))
        types = [fault_type(f) for f in self.faults]
        if len(set(types)) != len(types):
            raise ValueError(f"model {self.id!r} holds two sizes of one fault type: "
                             f"{sorted(self.faults)}")

    @property
    def fault_types(self) -> frozenset[str]:
        return frozenset(fault_type(f) for f in self.faults)


def sized_bank(fault_types: Sequence[str], *, sizes: Sequence[str] = SIZE_WORDS,
               max_faults: int = 2) -> list[BankModel]:
    """The bank of all fault combinations: nominal, singles in every size, doubles, ...

    Ids are ``"nominal"``, ``"fan_small"``, ``"fan_small+hub_large"`` (faults joined by ``+`` in
    the order of ``fault_types``). For ``("fan", "hub")`` and three sizes this is the paper's
    16-model bank in its numbering: 0 nominal, 1-3 fan small..large, 4-6 hub small..large,
    7-15 fan x hub (fan size major).
    """
    from itertools import combinations, product

    if len(set(fault_types)) != len(fault_types) or not fault_types:
        raise ValueError(f"fault_types must be distinct and non-empty: {fault_types}")
    bank = [BankModel(id="nominal")]
    for order in range(1, max_faults + 1):
        for types in combinations(fault_types, order):
            for szs in product(sizes, repeat=order):
                faults = [f"{ty}_{sz}" for ty, sz in zip(types, szs)]
                bank.append(BankModel(id="+".join(faults), faults=frozenset(faults)))
    return bank


def _check_bank(bank: Sequence[BankModel]) -> None:
    ids = [m.id for m in bank]
    if len(set(ids)) != len(ids):
        raise ValueError(f"duplicate model ids in bank: {ids}")
    if not any(not m.faults for m in bank):
        raise ValueError("the bank needs a nominal (fault-free) model")


def models_online(bank: Sequence[BankModel], isolated: Sequence[str]) -> list[str]:
    """Ids of the models to run given the isolated faults (the paper's bank rules).

    Parameters
    ----------
    bank : all models that exist, in bank order (the order is kept in the result).
    isolated : fault ids (or bare fault types) isolated so far, e.g. ``["hub_small"]``.

    Returns
    -------
    list of model ids: those whose fault types contain every isolated type and at most one
    more type (see the module docstring).
    """
    _check_bank(bank)
    known = {fault_type(f) for m in bank for f in m.faults}
    iso_types = frozenset(fault_type(f) for f in isolated)
    unknown = iso_types - known
    if unknown:
        raise ValueError(f"isolated fault(s) {sorted(unknown)} not represented in the bank")
    return [m.id for m in bank
            if iso_types <= m.fault_types and len(m.fault_types) <= len(iso_types) + 1]


def _norm_of(value: ResidualVector | float) -> tuple[float, bool, float | None]:
    """(|r|, valid, time stamp or None) of one entry of the residual mapping."""
    if isinstance(value, ResidualVector):
        norm = float(value.norm)
        return abs(norm), bool(value.valid) and math.isfinite(norm), float(value.t)
    norm = float(value)
    return abs(norm), math.isfinite(norm), None


@dataclass
class ExpertSupervisor:
    """Expert supervisory scheme of Diao & Passino (2004), section 3.2.

    Parameters
    ----------
    bank : all models (bank order fixes the numeric index I*, F*: position in this list).
    t0_s : hold time T0 [s]: a model must have the minimum residual for this long to be
        isolated (paper: 1.2 s).
    stale_s : a :class:`ResidualVector` older than ``t - stale_s`` [s] is ignored (its model
        node is late or dead); ``inf`` disables the check. Plain float norms carry no time and
        are always fresh.
    min_models : fewer valid on-line residuals than this gives state ``"not_valid"``
        (the minimum over one model says nothing).
    isolated : faults known to be present at start (default: none).

    Notes
    -----
    ``update`` is called once per sample (feature vector). Models missing from the mapping,
    stale or flagged invalid are skipped; if too few remain, the step is ``"not_valid"`` and
    the hold timer restarts (the supervisor never isolates across a gap). When a fault
    situation is isolated, the set of models on line changes by :func:`models_online`; the
    caller starts/stops model nodes accordingly (the returned ``Diagnosis.models_online``)
    and should reset the newly started models.
    """

    bank: Sequence[BankModel]
    t0_s: float
    stale_s: float = math.inf
    min_models: int = 2
    isolated: Sequence[str] = ()
    # running state (not constructor arguments)
    _online: list[str] = field(init=False, repr=False)
    _fault_model: str = field(init=False, repr=False)
    _run_model: str = field(init=False, repr=False, default="")
    _run_start: float = field(init=False, repr=False, default=math.nan)
    _detection_time: float = field(init=False, repr=False, default=math.nan)
    _isolation_time: float = field(init=False, repr=False, default=math.nan)
    _index: int = field(init=False, repr=False, default=0)
    history: list[tuple[float, str, str]] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.bank = tuple(self.bank)
        _check_bank(self.bank)
        if not (math.isfinite(self.t0_s) and self.t0_s >= 0):
            raise ValueError(f"t0_s must be a finite time >= 0 s, not {self.t0_s}")
        if not self.stale_s > 0:
            raise ValueError(f"stale_s must be > 0, not {self.stale_s}")
        if self.min_models < 1:
            raise ValueError("min_models must be >= 1")
        self._by_id = {m.id: m for m in self.bank}
        self._pos = {m.id: i for i, m in enumerate(self.bank)}
        self.reset(isolated=self.isolated)

    # -- state --------------------------------------------------------------------------------
    def reset(self, *, isolated: Sequence[str] = ()) -> None:
        """Forget the history; start with the given faults isolated."""
        self.isolated = tuple(sorted(isolated))
        self._online = models_online(self.bank, self.isolated)
        self._fault_model = self._model_for(self.isolated)
        self._run_model = ""
        self._run_start = math.nan
        self._detection_time = math.nan
        self._isolation_time = math.nan
        self._index = 0
        self.history = []

    def _model_for(self, faults: Sequence[str]) -> str:
        want = frozenset(faults)
        for m in self.bank:
            if m.faults == want:
                return m.id
        raise ValueError(f"no bank model represents the faults {sorted(want)}")

    @property
    def models_online(self) -> tuple[str, ...]:
        return tuple(self._online)

    @property
    def fault_model(self) -> str:
        """Id of the model currently believed to match the plant (nominal at start)."""
        return self._fault_model

    # -- one step -----------------------------------------------------------------------------
    def update(self, t: float,
               residuals: Mapping[str, ResidualVector | float]) -> Diagnosis:
        """Process the residuals of one sample at time ``t`` [s] and return the diagnosis.

        ``residuals`` maps model id -> :class:`ResidualVector` (its ``norm`` is used) or a plain
        residual value/norm; entries of models that are not on line are ignored.
        """
        t = float(t)
        if not math.isfinite(t):
            raise ValueError("update() needs a finite time")
        index = self._index
        self._index += 1
        best, best_norm, n_valid = "", math.inf, 0
        for mid in self._online:
            if mid not in residuals:
                continue
            norm, valid, stamp = _norm_of(residuals[mid])
            if not valid or (stamp is not None and stamp < t - self.stale_s):
                continue
            n_valid += 1
            if norm < best_norm:
                best, best_norm = mid, norm
        if n_valid < max(1, min(self.min_models, len(self._online))):
            self._run_model, self._run_start = "", math.nan
            return self._diagnosis(index, t, "not_valid", "", n_valid=n_valid)

        if best != self._run_model:
            self._run_model, self._run_start = best, t
            pending = self._detection_pending()
            if best != self._fault_model and not pending:
                # I*(k) left the current fault model: a (new) fault situation is detected
                self._detection_time = t
                self.history.append((t, "detected", best))
            elif best == self._fault_model and pending:
                self.history.append((t, "cleared", best))
        held = t - self._run_start >= self.t0_s - 1e-9
        if held and best != self._fault_model:
            self._isolate(best, t)
        if best == self._fault_model:
            state = "isolated" if self.isolated else "no_fault"
        else:
            state = "detected"
        return self._diagnosis(index, t, state, best, n_valid=n_valid)

    def _detection_pending(self) -> bool:
        """True while a detection has not yet been followed by an isolation or a return."""
        return bool(self.history) and self.history[-1][1] == "detected"

    def _isolate(self, model_id: str, t: float) -> None:
        self._fault_model = model_id
        self.isolated = tuple(sorted(self._by_id[model_id].faults))
        self._isolation_time = t
        self._online = models_online(self.bank, self.isolated)
        self.history.append((t, "isolated", model_id))

    def _diagnosis(self, index: int, t: float, state: str, best: str, *,
                   n_valid: int) -> Diagnosis:
        cand = tuple(sorted(self._by_id[best].faults)) if best else ()
        fm = self._fault_model
        return Diagnosis(
            index=index, t=t, state=state,
            min_residual_index=self._pos[best] if best else -1,
            min_residual_model=best,
            fault_index=self._pos[fm], fault_model=fm,
            candidate_faults=cand,
            isolated_faults=tuple(self.isolated),
            models_online=tuple(self._online),
            detection_time=self._detection_time,
            isolation_time=self._isolation_time,
            extra={"n_valid": n_valid,
                   "held_s": (t - self._run_start) if best else 0.0},
        )
