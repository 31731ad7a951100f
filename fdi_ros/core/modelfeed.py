"""Which feature vectors a bank model node answers, and from when.

Offline (:func:`fdi_ros.core.diagnoser.diagnose_offline`) a model that the bank switch of step
``k`` brings on line is reset and answers from step ``k + 1``. Live, the switch is decided at
step ``k`` while the source runs up to ``max_ahead_s`` ahead of the diagnosis: the features
``k + 1, k + 2, ...`` reach the model node before its activation, which comes through the
lifecycle services some wall time later, later still on a busy machine. A node that answered
only what it receives once active would start at a step that depends on the machine's speed,
and a model with a state (an open-loop simulation from the measured state at its start)
would give other residuals than offline.

So a node that is not active keeps the features it receives (the last ``keep``), follows the
diagnoses (index and models on line, ``/fdi/diagnosis``) and, once activated for the switch
that put it on line, answers the kept features after that step first, then the new ones:
the residuals of offline, however late the activation. An activation that comes before the
switch's diagnosis waits for it. Without a switch seen (start-up, a restarted node, an external
change undone) the node answers from the next features, as the supervisor expects then
(:class:`fdi_ros.core.supervision.SupervisorCore`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from typing import Generic, TypeVar

T = TypeVar("T")


class ModelFeed(Generic[T]):
    """The feature vectors (any item with its index) that model ``model_id`` must answer.

    Every method returns the items to answer now, in order; the node resets its model on
    activation, before answering the first of them.
    """

    def __init__(self, model_id: str, keep: int = 2000) -> None:
        if keep < 1:
            raise ValueError(f"keep must be >= 1, not {keep}")
        self.model_id = model_id
        self.active = False
        self.waiting = False  # activated, the diagnosis of the switch not seen yet
        self.listed: bool | None = None  # the last diagnosis lists the model (None: none yet)
        self.since: int | None = None  # the step whose switch listed it, while listed
        self._started = False  # answering for the current listing already
        self._kept: deque[tuple[int, T]] = deque(maxlen=keep)

    @property
    def answering(self) -> bool:
        """Active and started: every feature vector is answered as it comes; the diagnoses
        are not needed until the node leaves the active state (:meth:`deactivate`)."""
        return self.active and not self.waiting

    def features(self, index: int, item: T) -> list[T]:
        """Features ``index`` arrived (answered at once while answering, unless they are of a
        step up to the switch that put the model on line: features can reach the node after
        its activation although they were sent before the switch, and offline the model
        starts after it)."""
        if self.answering:
            return [item] if self.since is None or int(index) > self.since else []
        self._kept.append((int(index), item))
        return []

    def diagnosis(self, index: int, online: Iterable[str]) -> list[T]:
        """A diagnosis of step ``index`` with the models ``online`` after it."""
        listed = self.model_id in set(online)
        if listed and self.listed is False:
            self.since, self._started = int(index), False  # the switch of step ``index``
        elif not listed:
            self.since = None
        self.listed = listed
        if self.waiting and self.since is not None:
            return self._from_switch()
        return []

    def activate(self) -> list[T]:
        """The node became active."""
        self.active = True
        if self.listed and self.since is not None and not self._started:
            return self._from_switch()
        if self.listed is False:  # the switch's diagnosis is still on its way
            self.waiting = True
            return []
        self._started = True  # no switch seen: from the next features on
        self._kept.clear()
        return []

    def deactivate(self) -> None:
        """The node left the active state."""
        self.active = self.waiting = False
        self._kept.clear()

    def _from_switch(self) -> list[T]:
        since = self.since if self.since is not None else -1
        out = [x for i, x in self._kept if i > since]
        self._kept.clear()
        self.waiting, self._started = False, True
        return out
