"""Physical constants: the one source for every model, simulator and analysis of the project.

Air is an ideal gas with the specific gas constant of dry air, R_AIR = R / M_air.
"""

from __future__ import annotations

R_UNIVERSAL = 8.314462618  # J/(mol K), molar gas constant (CODATA 2018, exact)
M_AIR = 0.0289647  # kg/mol, molar mass of dry air (ISO 2533 standard atmosphere)
R_AIR = R_UNIVERSAL / M_AIR  # J/(kg K), 287.05
