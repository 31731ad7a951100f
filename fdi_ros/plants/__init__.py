"""Plant wings: one sub-package per plant (simulator or measured-data source, scenarios,
preprocessor, residual-model kinds, identification, bank builder, fault-symptom table, figures,
reproduction). The generic core in ``fdi_ros.core`` names no plant."""
