"""Build the LiU-ICE bank's residual set when a graph configuration needs it (fault-free
benchmark files only; ``FDI_LIU_ICE_DATA`` or ``../shared/data/liu_ice`` holds them)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

from fdi_ros.plants.liu_ice import FAULT_FREE, ROOT
from fdi_ros.plants.liu_ice.residuals import MODEL_FILE

DEFAULT_DATA = ROOT.parent / "shared" / "data" / "liu_ice"


def data_dir() -> Path:
    return Path(os.environ.get("FDI_LIU_ICE_DATA", DEFAULT_DATA))


def ensure_bank(cfg, *, progress: bool = False, log: Callable[[str], None] = print,
                **_: object) -> list[str]:
    """Identify the residual set into every model directory of the bank that lacks one."""
    from fdi_ros.plants.liu_ice.identify import identify
    from fdi_ros.plants.liu_ice.live import load_record

    dirs: dict[str, list[str]] = {}
    for e in cfg.bank:
        spec = cfg.resolve_spec(e.model)
        if isinstance(spec, dict) and spec.get("type") == "liu_ice_structured":
            model_dir = Path(spec.get("path", "."))
            if not (model_dir / MODEL_FILE).is_file():
                dirs.setdefault(str(model_dir), []).append(e.id)
    built = []
    for d, ids in dirs.items():
        src = data_dir()
        files = [src / f for f in FAULT_FREE]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise FileNotFoundError(f"the LiU-ICE residual set needs the fault-free files "
                                    f"{missing} (set FDI_LIU_ICE_DATA)")
        t0 = time.perf_counter()
        identify([load_record(f) for f in files]).save(d)
        log(f"[bank] LiU-ICE residual set identified on {', '.join(FAULT_FREE)} -> {d} "
            f"({time.perf_counter() - t0:.1f} s)")
        built += ids
    return built
