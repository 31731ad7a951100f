"""Training of the turbofan node models (TS fuzzy, Levenberg-Marquardt).

Simulates every node of the grid in ``config/turbofan.yaml`` (operating conditions x
deterioration x fault sizes) on 20 s of transient data and fits F1 (XNLdot) and F2 (XNHdot) per
node and writes the global model (npz, a regenerated artifact under build/) with its training
report (time, node count, fit errors).
"""

from __future__ import annotations


def train(settings, *, out=None, seed=None, progress=True, fit_widths=False):
    """Train and save the global model of ``settings``; returns (model, path, width fit)."""
    import numpy as np

    from fdi_ros.plants.turbofan import bank as tfb
    from fdi_ros.plants.turbofan import models as tfm

    gm = tfm.train_global(settings.grid, n_rules=settings.n_rules,
                          seed=settings.training_seed if seed is None else seed,
                          duration_s=settings.training_duration_s, max_nfev=settings.max_nfev,
                          progress=progress)
    fit = None
    if fit_widths:
        extra = []
        for m in tfb.PAPER_BANK:  # the bank's own situations, on the fault nodes
            u = tfb.fault_units(m.faults)
            extra.append([*settings.condition, settings.deterioration, u["fan"], u["hub"]])
        gm, fit = tfm.fit_widths(gm, extra_points=np.array(extra))
    path = gm.save(out or settings.model_path)
    return gm, path, fit
