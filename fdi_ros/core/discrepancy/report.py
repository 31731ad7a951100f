"""Report of a discrepancy analysis: Markdown + PNG figures (matplotlib, Agg).

Figures: the channel and its residual over time before/after the extension (with the onset
of abrupt findings marked), the error map over the model's operating region, the residual
spectrum by crank-angle order (or by frequency for mean-value data), the held-out ranking of
all candidates, and the residual's correlation with every measured signal the model does not
use (including time derivatives).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fdi_ros.core.discrepancy.context import build_contexts
from fdi_ros.core.discrepancy.engine import Candidate, DiscrepancyResult, format_params
from fdi_ros.core.discrepancy.model import ExtendedModel
from fdi_ros.core.measured import Measured, segment_means


def _save(fig: Any, out: Path, name: str, caption: str, figs: list[tuple[str, str]]) -> None:
    """Lay out, write and close one report figure; list it with its caption."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(out / name, dpi=90)
    plt.close(fig)
    figs.append((name, caption))

def error_map(region: dict[str, np.ndarray], resid: np.ndarray, bins: int = 8
              ) -> tuple[list[str], list[np.ndarray], np.ndarray, np.ndarray]:
    """Mean residual per (quantile) bin of the first two region axes: (edges, mean, count)."""
    names = list(region)[:2]
    ok = np.isfinite(resid)
    for n in names:
        ok &= np.isfinite(region[n])
    # uniform bins between the 1st and 99th percentiles read better than quantile bins
    edges = []
    for n in names:
        lo, hi = np.quantile(region[n][ok], [0.01, 0.99])
        hi = hi if hi > lo else lo + 1.0
        edges.append(np.linspace(lo, hi, bins + 1))
    idx = [np.clip(np.searchsorted(e, region[n][ok], side="right") - 1, 0, len(e) - 2)
           for e, n in zip(edges, names)]
    shape = tuple(len(e) - 1 for e in edges)
    flat = np.ravel_multi_index(idx, shape)
    cnt = np.bincount(flat, minlength=int(np.prod(shape))).reshape(shape)
    s = np.bincount(flat, weights=resid[ok], minlength=int(np.prod(shape))).reshape(shape)
    mean = np.where(cnt >= 10, s / np.maximum(cnt, 1), np.nan)
    return names, edges, mean, cnt


def order_spectrum(alpha: np.ndarray, resid: np.ndarray, orders: np.ndarray) -> np.ndarray:
    """Amplitude of the least-squares fit ``a cos + b sin`` of the residual per order."""
    ok = np.isfinite(resid) & np.isfinite(alpha)
    r, a = resid[ok], alpha[ok]
    amp = []
    for k in orders:
        th = 2 * np.pi * k * a / 180.0
        A = np.stack([np.cos(th), np.sin(th)], axis=1)
        c, *_ = np.linalg.lstsq(A, r, rcond=None)
        amp.append(float(np.hypot(*c)))
    return np.array(amp)


def runner_up(result: DiscrepancyResult) -> tuple[Candidate, Candidate, bool] | None:
    """(top candidate, runner-up candidate, scored jointly) of the top finding's step 1, or
    None.

    The runner-up is the best candidate of another effect or signal (a variant of the same
    effect, e.g. after an onset vs always on, is not a competing explanation). Where other
    residuals checked the leading explanations, both come from that joint scoring (every
    residual each explanation moves, in units of its noise level): what the choice was made
    on; else from the channel's own candidate table.
    """
    if not result.findings:
        return None
    top = result.findings[0]
    for pool, joint in ((result.joint, True), (result.candidates, False)):
        first = next((c for c in pool if c.label == top.label and c.channel == top.channel),
                     None)
        if first is None:
            continue
        same = sorted((c for c in pool if c.mse_blocks.size == first.mse_blocks.size
                       and (c.effect, c.channel) != (top.effect, top.channel)),
                      key=lambda c: float(np.nanmean(c.mse_blocks)))
        if same:
            return first, same[0], joint
    return None


def _evidence_figure(plt: Any, out: Path, result: DiscrepancyResult
                     ) -> tuple[str, str] | None:
    pair = runner_up(result)
    if pair is None:
        return None
    a, b, joint = pair
    blocks = np.arange(a.mse_blocks.size)
    fig, ax = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True)
    ax[0].plot(blocks, np.sqrt(a.mse_blocks), "o-", ms=3, label=f"top: {a.label} on "
               f"{a.channel} ({a.gain_pct:.1f} %, p_adj {a.p_adjusted:.2g})")
    ax[0].plot(blocks, np.sqrt(b.mse_blocks), "s-", ms=3, label=f"runner-up: {b.label} on "
               f"{b.channel} ({b.gain_pct:.1f} %, p_adj {b.p_adjusted:.2g})")
    ax[0].set_ylabel("held-out score (RMS, each residual\nin units of its noise level)")
    ax[0].legend(fontsize=8)
    d = b.mse_blocks - a.mse_blocks
    ax[1].bar(blocks, d, color=["C2" if v > 0 else "C3" for v in d])
    ax[1].axhline(0, color="k", lw=0.5)
    ax[1].set_ylabel("runner-up - top")
    ax[1].set_xlabel("held-out block (in time order)")
    ax[0].set_title("Evidence: the top finding against the best other explanation, block by "
                    "block" + ("\n(scored on every residual it moves)" if joint else ""),
                    fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "evidence_top_vs_runner_up.png", dpi=90)
    plt.close(fig)
    return ("evidence_top_vs_runner_up.png",
            f"Evidence: {a.label} against the runner-up {b.label} on {b.channel} on held-out "
            f"blocks{', scored on every residual each moves' if joint else ''} (green: the "
            f"top finding predicts the block better)")


def write_report(out_dir: str | Path, data: Measured, baseline: Any, extended: ExtendedModel,
                 result: DiscrepancyResult, *, title: str = "Discrepancy analysis") -> Path:
    """Write ``index.md`` and the PNGs into ``out_dir``; returns the Markdown path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    crank = data.alpha is not None and bool(getattr(baseline, "orders", ()))
    if data.alpha is not None and not crank:
        data = segment_means(data)  # a mean-value model is compared on segment means
    view = segment_means(data) if crank else data
    base_view = baseline.without_pulsation() if crank else baseline
    ctxs = build_contexts(view, base_view)
    ext_pred = extended.predict(view)
    figs: list[tuple[str, str]] = []
    for ch, ctx in ctxs.items():
        r0 = ctx.y - ctx.yhat
        r1 = ctx.y - ext_pred[ch]
        unit = ctx.unit
        # 1. channel and residual over time
        fig, ax = plt.subplots(2, 1, figsize=(11, 6), sharex=True)
        ax[0].plot(ctx.t, ctx.y, lw=0.7, label=f"measured {ch}")
        ax[0].plot(ctx.t, ctx.yhat, lw=0.7, label="baseline model")
        ax[0].plot(ctx.t, ext_pred[ch], lw=0.7, ls="--", label="extended model")
        ax[0].set_ylabel(f"{ch} [{unit}]")
        ax[0].legend(loc="upper right", fontsize=8)
        ax[1].plot(ctx.t, r0, lw=0.6, label=f"baseline (RMSE {np.sqrt(np.nanmean(r0**2)):.3g})")
        ax[1].plot(ctx.t, r1, lw=0.6, label=f"extended (RMSE {np.sqrt(np.nanmean(r1**2)):.3g})")
        ax[1].axhline(0, color="k", lw=0.5)
        for f in result.findings:
            on = f.params.get("onset_s") if f.channel == ch else None
            if on is not None:
                for a in ax:
                    a.axvline(on, color="r", ls=":", lw=1)
                ax[1].text(on, np.nanmax(r0), f" onset {on:.1f} s ({f.effect})", color="r",
                           fontsize=8, va="top")
        ax[1].set_ylabel(f"residual [{unit}]")
        ax[1].set_xlabel("time [s]")
        ax[1].legend(loc="upper left", fontsize=8)
        ax[0].set_title(f"{ch}: measured vs model" + (" (180 deg CA segment means)"
                                                     if view.alpha is None and "segment" in
                                                     view.source else ""))
        _save(fig, out, f"residual_time_{ch}.png",
              "Measured channel, baseline and extended model; residual over time", figs)
        # 2. error map over the operating region
        if len(ctx.region) >= 2:
            names, edges, mean, cnt = error_map(ctx.region, r0)
            fig, ax = plt.subplots(figsize=(7, 5.2))
            lim = np.nanmax(np.abs(mean)) if np.isfinite(mean).any() else 1.0
            pc = ax.pcolormesh(edges[0], edges[1], mean.T, cmap="RdBu_r", vmin=-lim, vmax=lim)
            fig.colorbar(pc, ax=ax, label=f"mean residual [{unit}]")
            for i in range(mean.shape[0]):
                for j in range(mean.shape[1]):
                    if cnt[i, j] >= 10:
                        ax.text(0.5 * (edges[0][i] + edges[0][i + 1]),
                                0.5 * (edges[1][j] + edges[1][j + 1]), f"{mean[i, j]:.2g}",
                                ha="center", va="center", fontsize=7)
            for f in result.findings:
                if f.effect == "local_region" and f.channel == ch and f.params.get("region"):
                    reg = f.params["region"]
                    (x0, x1), (y0, y1) = reg[names[0]], reg[names[1]]
                    x0, x1 = max(x0, edges[0][0]), min(x1, edges[0][-1])
                    y0, y1 = max(y0, edges[1][0]), min(y1, edges[1][-1])
                    ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False,
                                               ec="k", lw=2, ls="--"))
            ax.set_xlabel(f"{names[0]} [{data.units.get(names[0], '')}]")
            ax.set_ylabel(f"{names[1]} [{data.units.get(names[1], '')}]")
            ax.set_title(f"Error map of {ch} (baseline): mean residual per bin (>= 10 samples)")
            _save(fig, out, f"error_map_{ch}.png",
                  "Where in the operating region the baseline is wrong", figs)
        # 3. correlation with unused signals
        cols = dict(ctx.columns)
        if cols:
            cc = {}
            for k, v in cols.items():
                ok = np.isfinite(v) & np.isfinite(r0)
                if ok.sum() > 10 and np.std(v[ok]) > 0:
                    cc[k] = float(np.corrcoef(v[ok], r0[ok])[0, 1])
            keys = sorted(cc, key=lambda k: -abs(cc[k]))[:15]
            fig, ax = plt.subplots(figsize=(8, 0.35 * len(keys) + 1.2))
            ax.barh(range(len(keys)), [cc[k] for k in keys],
                    color=["C3" if cc[k] > 0 else "C0" for k in keys])
            ax.set_yticks(range(len(keys)), keys, fontsize=8)
            ax.invert_yaxis()
            ax.axvline(0, color="k", lw=0.5)
            ax.set_xlabel("correlation with the baseline residual")
            ax.set_title(f"{ch}: residual vs measured signals the model does not use")
            _save(fig, out, f"correlation_{ch}.png",
                  "Candidate explanations: correlation of the residual", figs)
    # 4. spectrum: by crank-angle order, or by frequency
    if crank and data.alpha is not None:
        alpha = data.alpha
        cctx = build_contexts(data, baseline)
        pred = extended.predict(data)
        orders = np.arange(0.5, min(8.0, 0.45 * 180.0 / float(np.median(np.diff(alpha))))
                           + 1e-9, 0.5)
        fig, ax = plt.subplots(figsize=(9, 4))
        for ch, ctx in cctx.items():
            a0 = order_spectrum(alpha, ctx.y - ctx.yhat, orders)
            a1 = order_spectrum(alpha, ctx.y - pred[ch], orders)
            ax.bar(orders - 0.1, a0, width=0.2, label=f"{ch} baseline residual")
            ax.bar(orders + 0.1, a1, width=0.2, label=f"{ch} extended")
        ax.set_xlabel("order (multiples of the 180 deg CA fundamental)")
        ax.set_ylabel("amplitude")
        ax.set_title("Residual spectrum by crank-angle order")
        ax.legend(fontsize=8)
        _save(fig, out, "order_spectrum.png", "Residual spectrum by crank-angle order", figs)
    else:
        from scipy.signal import welch

        fig, ax = plt.subplots(figsize=(9, 4))
        for ch, ctx in ctxs.items():
            for lab, r in (("baseline", ctx.y - ctx.yhat), ("extended", ctx.y - ext_pred[ch])):
                ok = np.isfinite(r)
                f, pxx = welch(np.where(ok, r, 0.0), fs=1.0 / ctx.dt,
                               nperseg=min(512, ok.sum()))
                ax.semilogy(f[1:], pxx[1:], label=f"{ch} {lab}")
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel("residual PSD")
        ax.set_title("Residual spectrum (no crank-angle data: by frequency)")
        ax.legend(fontsize=8)
        _save(fig, out, "residual_spectrum.png", "Residual spectrum by frequency", figs)
    # 5. evidence for the top finding against its runner-up, block by block
    ev = _evidence_figure(plt, out, result)
    if ev:
        figs.append(ev)
    # 6. candidate ranking
    cands = result.candidates[:15]
    if cands:
        fig, ax = plt.subplots(figsize=(8, 0.35 * len(cands) + 1.2))
        gains = [c.gain_pct for c in cands]
        sig = [c.p_adjusted < result.config.alpha and c.gain_pct >= result.config.min_gain_pct
               for c in cands]
        ax.barh(range(len(cands)), gains, color=["C2" if s else "0.6" for s in sig])
        ax.set_yticks(range(len(cands)), [f"{c.label} ({c.channel})" for c in cands],
                      fontsize=8)
        ax.invert_yaxis()
        ax.set_xlabel("held-out RMSE gain [%] (green: significant)")
        ax.set_title("Every candidate extension, first step, held-out blocks")
        _save(fig, out, "candidates.png", "Held-out gain of every candidate extension", figs)
    # Markdown
    lines = [f"# {title}", "", f"Data: `{data.source}` ({data.n_samples} samples, "
             f"{data.t[-1] - data.t[0]:.1f} s). Verdict: **{result.verdict}**: {result.message}.",
             "", "| rank | effect | channel (view) | parameters | RMSE before | RMSE after "
             "(held-out) | gain | p (adj.) |", "|---|---|---|---|---|---|---|---|"]
    for f in result.findings:
        lines.append(f"| {f.rank} | {f.label} | {f.channel} ({f.view}) | "
                     f"{format_params(f.params)} | "
                     f"{f.rmse_before:.4g} | {f.rmse_after:.4g} | {f.gain_pct:.1f} % | "
                     f"{f.p_adjusted:.2g} |")
    if not result.findings:
        lines.append("| - | none significant | | | | | | |")
    sus = result.suspect
    if sus is not None:
        lines.append(f"\nNot significant, but the best explanation over every residual: "
                     f"**{sus.label}** on {sus.channel} ({format_params(sus.params)}), held-out "
                     f"gain {sus.gain_pct:.1f} % on {sus.shown_on}, p (adj.) "
                     f"{sus.p_adjusted:.2g}; moves {', '.join(sus.residuals)}. The data cannot "
                     "tell it from: " + ("; ".join(f"{a['label']} on {a['channel']} "
                                                   f"({format_params(a['params'])})"
                                                   for a in sus.alternatives) or "none")
                     + ". More data after the change, or where it acts most, would decide.")
    for f in result.findings:
        for a in f.alternatives:
            if "separate_by" in a:  # a tie with another sensor: why, and what separates
                lines.append(f"\nFinding {f.rank} ({f.label} on {f.channel}) is **tied** with "
                             f"**{a['label']}** ({format_params(a['params'])}): {a['why']}. "
                             f"Would separate them: {a['separate_by']}.")
                continue
            lines.append(f"\nFinding {f.rank} ({f.label}) is indistinguishable on the held-out "
                         f"blocks from **{a['label']}** (gain {a['gain_pct']:.1f} %): "
                         f"{format_params(a['params'])}.")
    lines += ["", "Held-out scheme: contiguous time blocks, each held out in turn (guard bands "
              "around it); significance: Wilcoxon signed-rank over the blockwise held-out MSE, "
              "Bonferroni over the channel's own candidates (the errors of the model's input "
              "sensors compete for the attribution); ties: explanations not significantly "
              "worse than the top one.", ""]
    for name, cap in figs:
        lines += [f"## {cap}", "", f"![{cap}]({name})", ""]
    md = out / "index.md"
    md.write_text("\n".join(lines))
    return md
