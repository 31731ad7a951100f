"""Turbofan seed (Diao & Passino 2004): plant simulator, Takagi-Sugeno models, model bank."""
