"""LiU-ICE: a real turbocharged gasoline engine on a test bench (measured data, 20 Hz).

The LiU-ICE Industrial Fault Diagnosis Benchmark (Linkoping University; D. Jung, E. Frisk,
M. Krysander, arXiv:2408.13269; the DX 2025 diagnosis competition). A mean-value,
time-synchronous plant: no crank angle, one feature vector per sample. Its "simulator" is
measured data: a CSV window with the column mapping ``config/mappings/liu_ice.yaml``, imported
into a bag by ``fdi-ros import`` and replayed into the graph.

Fault classes (the benchmark's names): ``f_pic`` boost (intercooler) pressure sensor gain,
``f_pim`` intake manifold pressure sensor gain, ``f_waf`` air-mass-flow sensor gain, ``f_iml``
intake manifold leak.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]  # the repository (config/, build/)
PLANT = "liu_ice"
DISPLACEMENT_L = 1.953
FAULT_FREE = ("ftp75city2_NF.csv", "wltp_NF.csv")
FAULT_CLASSES = ("f_pic", "f_pim", "f_waf", "f_iml")
# The sensor or process part each fault class acts on (decides its fault-symptom column).
FAULT_ACTS_ON = {"f_pic": "p_ic", "f_pim": "p_im", "f_waf": "maf", "f_iml": "manifold"}
# Signals of a feature vector, in the order of the sensor blocks.
CHANNELS = ("n", "p_im", "p_ic", "maf", "throttle", "wastegate", "T_im", "p_amb", "T_amb",
            "fuel")
UNITS = ("rpm", "Pa", "Pa", "kg/h", "%", "1", "K", "Pa", "K", "")

# Fault onsets of the benchmark's files [s] (its fault-time table; the leak "about 120 s").
KNOWN_ONSETS_S = {
    "ftp75city2_f_waf_110.csv": 122.45,
    "ftp75city2_f_waf_090.csv": 125.05,
    "ftp75city2_f_pim_090.csv": 123.30,
    "ftp75city2_f_pim_110.csv": 123.00,
    "ftp75city2_f_pic_090.csv": 128.05,
    "wltp_f_iml_6mm.csv": 117.55,
}
_NAME = re.compile(r"^(?P<cycle>.+?)_(?:(?P<nf>NF)|(?P<fault>f_(?:pic|pim|waf|iml))_"
                   r"(?P<size>[0-9]+(?:mm)?))$")


@dataclass(frozen=True)
class FileTruth:
    """Ground truth of one benchmark file: fault class ("" for none), size, onset [s]."""

    fault: str = ""
    gain: float = 1.0          # sensor gain faults: reading = gain x true value
    size: float = 0.0          # the leak: orifice diameter [mm]
    size_unit: str = "1"
    onset_s: float = float("nan")

    @property
    def faulty(self) -> bool:
        return bool(self.fault)


def truth_of(path: str | Path, onset_s: float | None = None, *,
             unlabelled_ok: bool = False) -> FileTruth:
    """Ground truth from a benchmark file name (``<cycle>_NF.csv``, ``<cycle>_f_waf_110.csv``:
    gain 1.10, ``<cycle>_f_iml_6mm.csv``: 6 mm leak) and the known onsets.

    Raises ValueError for a name that carries no label (``unlabelled_ok``: no fault known,
    i.e. no ground truth), and for a fault file whose onset is neither in the table nor given.
    """
    name = Path(path).name
    m = _NAME.match(Path(name).stem)
    if m is None and unlabelled_ok:
        return FileTruth()
    if m is None:
        raise ValueError(f"{name}: not a LiU-ICE benchmark file name (<cycle>_NF.csv or "
                         f"<cycle>_<f_pic|f_pim|f_waf|f_iml>_<size>.csv)")
    if m.group("nf"):
        return FileTruth()
    fault, size = m.group("fault"), m.group("size")
    onset = KNOWN_ONSETS_S.get(name, onset_s)
    if onset is None:
        raise ValueError(f"{name}: fault onset unknown (give it with --onset)")
    if fault == "f_iml":
        return FileTruth(fault=fault, size=float(size.removesuffix("mm")), size_unit="mm",
                         onset_s=float(onset))
    gain = int(size) / 100.0
    return FileTruth(fault=fault, gain=gain, size=gain, onset_s=float(onset))
