"""The LiU-ICE wing for the plant registry of ``fdi_ros.plants`` (``WING``): measured data as
the plant, one feature vector per sample, the structured residual models, the bank builder.

Listed in the registry's table as ``"liu_ice": "fdi_ros.plants.liu_ice.wing"``.
"""

from __future__ import annotations

from fdi_ros.core.types import FaultEvent
from fdi_ros.plants import Wing
from fdi_ros.plants.liu_ice import FAULT_CLASSES, PLANT, ROOT
from fdi_ros.plants.liu_ice.bank import ensure_bank
from fdi_ros.plants.liu_ice.live import INJECTABLE, LiuIcePreprocessor, MeasuredRunner


def validate_fault(event: FaultEvent) -> None:
    """Measured data takes sensor gain faults only (a leak is a process fault)."""
    if event.fault and event.fault not in INJECTABLE:
        raise ValueError(f"measured data can only be given sensor gain faults "
                         f"{sorted(INJECTABLE)}, not {event.fault!r}")
    if event.fault and not 0.5 <= event.size <= 2.0:
        raise ValueError(f"gain {event.size} outside [0.5, 2]")


WING = Wing(
    name=PLANT,
    runner=MeasuredRunner,
    preprocessor=LiuIcePreprocessor,
    kinds={"fdi_ros.plants.liu_ice.residuals": ("liu_ice_structured",)},
    faults=FAULT_CLASSES,
    validate_fault=validate_fault,
    build_bank=ensure_bank,
    fst=ROOT / "docs" / "liu_ice_fst.json",
)
