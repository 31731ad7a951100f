"""``fdi-ros figures diesel-plant``: the diesel plant's figures as in Schwarte & Isermann 2002.

* ``fig4_maf_segment.png``: MAF over one 180 deg CA segment at 1200 rpm with its mean and
  one-harmonic approximation (the paper's Fig. 4).
* ``fig7_ident_coverage.png``: the identification cycle's segment features in the
  (engine speed, boost density) plane (the paper's Fig. 7).
* ``ident_features.png``: eta_V, MAF amplitude and phase over speed from the same cycle
  (what the reference models of the paper's Figs. 8-10 are identified from).
"""

from __future__ import annotations

import argparse
import json

COMMAND = ("figures", "diesel-plant")
HELP = "save the diesel plant figures (MAF segment fit, identification-cycle coverage) as PNG"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out-dir", default="figures", help="directory for the PNGs")
    parser.add_argument("--scenario", default=None,
                        help="identification scenario "
                             "(default config/scenarios/diesel_ident.yaml)")
    parser.add_argument("--seed", type=int, default=None, help="noise seed override")


def _save(fig, path, written: list[str], *, tight: bool = True) -> None:
    import matplotlib.pyplot as plt
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    written.append(str(path))


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from fdi_ros.plants.diesel.plant import DieselIntakePlant, crank_segmenter, fuel_for_torque
    from fdi_ros.plants.diesel.scenario import simulate

    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scen = args.scenario
    if scen is None:
        scen = Path(__file__).resolve().parents[2] / "config" / "scenarios" / "diesel_ident.yaml"
    written: list[str] = []

    # --- Fig. 4: one segment at 1200 rpm with the one-harmonic fit
    plant = DieselIntakePlant(seed=0 if args.seed is None else args.seed)
    n = 1200.0
    plant.set_inputs(n_rpm=n, fuel_mg=float(fuel_for_torque(n, 80.0, plant.p)))
    block = plant.advance(int(6 * n * 4))
    tab = crank_segmenter(plant.p).push_table(block)
    j = tab.index.size - 2
    a0 = tab.alpha_start[j]
    m = (block.alpha >= a0) & (block.alpha <= a0 + 180.0)
    a = block.alpha[m] - a0
    maf = block.channel("maf")[m]
    mean, amp, ph = (tab.column(k)[j] for k in ("maf", "maf_amp", "maf_phase"))
    fit = mean + amp * np.cos(2 * np.pi * a / 180.0 + np.radians(2.0 * ph))
    fig, ax = plt.subplots(figsize=(7.0, 4.2))
    ax.plot(a, maf, ".", ms=3, color="0.45", label="MAF samples (1 deg CA)")
    ax.plot(a, fit, "-", lw=2, color="C3", label="mean + first harmonic")
    ax.axhline(mean, color="C0", lw=1, ls="--", label=f"mean {mean:.1f} kg/h")
    a_max = (-ph) % 180.0
    ax.annotate("", xy=(a_max, mean + amp), xytext=(a_max, mean),
                arrowprops=dict(arrowstyle="<->", color="C2"))
    ax.text(a_max + 3, mean + amp / 2, f"A = {amp:.1f} kg/h", color="C2")
    ax.set_xlim(0, 180)
    ax.set_xlabel(f"crank angle within segment [deg CA] (segment start {a0:.0f} deg CA)")
    ax.set_ylabel("air mass flow [kg/h]")
    ax.set_title(f"MAF over one 180 deg CA segment, {n:.0f} rpm: phase {ph:.1f} deg CA")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    _save(fig, out / "fig4_maf_segment.png", written)

    # --- Fig. 7 and the feature overview from the identification cycle
    res = simulate(scen, seed=args.seed, keep_blocks=False)
    F = res.features
    ok = F.valid
    nn, rho = F.column("n")[ok], F.column("rho2")[ok]
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    step = max(1, nn.size // 6000)
    ax.plot(nn[::step], rho[::step], ".", ms=2, color="C0", alpha=0.6)
    ax.set_xlabel("engine speed n [rpm]")
    ax.set_ylabel("boost density rho2 [kg/m^3]")
    ax.set_title(f"Identification cycle coverage ({ok.sum()} segments, "
                 f"{res.scenario.duration_s:.0f} s)")
    ax.text(0.03, 0.95, "low speed + high boost:\nnot reachable", transform=ax.transAxes,
            va="top", fontsize=9, color="0.3")
    ax.grid(alpha=0.3)
    _save(fig, out / "fig7_ident_coverage.png", written)

    fig, axs = plt.subplots(2, 2, figsize=(10, 7.5))
    for ax, (k, lab) in zip(axs.flat, [("eta_v", "eta_V [1]"), ("maf_amp", "A_maf [kg/h]"),
                                        ("maf_phase", "phi_maf [deg CA]"),
                                        ("p2_amp", "A_p2 [Pa]")]):
        sc = ax.scatter(nn[::step], F.column(k)[ok][::step], c=rho[::step], s=2,
                        cmap="viridis")
        ax.set_xlabel("n [rpm]")
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
    fig.colorbar(sc, ax=axs, label="rho2 [kg/m^3]", shrink=0.8)
    fig.suptitle("Identification-cycle segment features (EGR closed, swirl open)")
    _save(fig, out / "ident_features.png", written, tight=False)
    print(json.dumps({"figures": written, "segments": int(ok.sum())}))
    return 0
