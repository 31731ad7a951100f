"""Figures like Diao & Passino (2004) Figs. 4-7 and the T0 sweep (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fdi_ros.plants.turbofan.bank import ScenarioResult

STYLES = ["-", ":", "-.", "--", ":", "-.", "--"]


def case_figure(res: ScenarioResult, path: str | Path, *, xnh_weight: float = 0.0) -> Path:
    """Four panels: XN2 (plant and the models on line at start or end), residual norms of the
    models while on line, the minimum-residual index I*(k), the fault index F*(k) (bank
    numbering 0-15)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = res.t
    ids = list(res.model_ids)
    shown = sorted({ids.index(m) for online in (res.online[0], res.online[-1]) for m in online})
    fig, ax = plt.subplots(4, 1, figsize=(10.5, 10), sharex=True, layout="constrained")
    ax[0].plot(t, res.y[:, 0], "k", lw=2.2, label="engine XN2")
    cmap = plt.get_cmap("tab20")
    for j, i in enumerate(shown):
        kw = dict(color=cmap(i % 20), ls=STYLES[j % len(STYLES)], lw=1.0 if i < 4 else 1.6)
        ax[0].plot(t, res.yhat[i], label=f"{i}: {ids[i]}", **kw)
        on = np.array([ids[i] in online for online in res.online])
        ax[1].plot(t, np.where(on, res.norms[i], np.nan), **kw)  # only while on line
    ax[0].set_ylabel("XN2 [rpm]")
    ax[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.02))
    lo, hi = np.percentile(res.y[:, 0], [0, 100])
    ax[0].set_ylim(lo - 120, hi + 40)
    ax[1].set_ylabel("residual norm [rpm]" if xnh_weight else "|residual| [rpm]")
    ax[1].set_ylim(0, 100)
    ax[2].step(t, res.min_index, where="post", color="tab:blue")
    ax[2].set_ylabel("minimum residual\nindex I*")
    ax[3].step(t, res.fault_index, where="post", color="tab:red")
    ax[3].set_ylabel("fault index F*")
    for a in ax[2:]:
        a.set_ylim(-0.5, 15.5)
        a.set_yticks(range(0, 16, 3))
        a.grid(alpha=0.3)
    for te, _ in res.scenario.events:
        for a in ax:
            a.axvline(te, color="grey", lw=0.8, ls="--")
    for tk, kind, m in res.history:
        if kind == "isolated":
            ax[3].annotate(f"{m}\n{tk:.2f} s", (tk, ids.index(m)), fontsize=7,
                           xytext=(4, 4), textcoords="offset points")
    ax[3].set_xlabel("time [s]")
    ax[0].set_title(f"turbofan case {res.scenario.name}")
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def sweep_figure(sweep: list[dict], path: str | Path, *, paper_delay: float) -> Path:
    """False isolations (fault-free runs + wrong isolations in the cases) against mean
    isolation delay, one point per T0."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = np.array([s["t0_s"] for s in sweep])
    false_ff = np.array([s["fault_free_false_isolations"] for s in sweep])
    false_wide = np.array([s.get("fault_free_false_isolations_twice_sigma", 0) for s in sweep])
    wrong = np.array([s["wrong_isolations_in_cases"] for s in sweep])
    delay = np.array([s["mean_isolation_delay_s"] for s in sweep])
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    ax[0].plot(t0, false_ff, "o-", color="tab:blue", label="false isolations, fault-free runs")
    ax[0].plot(t0, false_wide, "x:", color="tab:orange",
               label="false isolations, 2x manufacturing spread")
    ax[0].plot(t0, wrong, "s--", color="tab:red", label="wrong isolations, fault cases")
    ax[0].set_xlabel("hold time T0 [s]")
    ax[0].set_ylabel("count")
    ax0b = ax[0].twinx()
    ax0b.plot(t0, delay, "^-", color="tab:green", label="mean isolation delay")
    ax0b.axhline(paper_delay, color="tab:green", ls=":", lw=1)
    ax0b.set_ylabel("mean isolation delay [s]", color="tab:green")
    ax[0].legend(fontsize=8, loc="center right")
    total = false_ff + wrong
    ax[1].plot(delay, total, "o-")
    for j, (x, y, t) in enumerate(zip(delay, total, t0)):
        ax[1].annotate(f"T0={t:g}", (x, y), fontsize=7, xytext=(3, 4 if j % 2 else -10),
                       textcoords="offset points")
    ax[1].axvline(paper_delay, color="grey", ls="--", label=f"paper, {paper_delay:.2f} s")
    ax[1].set_xlabel("mean isolation delay [s]")
    ax[1].set_ylabel("false + wrong isolations")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
