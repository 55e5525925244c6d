"""Learned probabilistic-ensemble dynamics and uncertainty-aware planning costs (thesis chapter 5, appendix D)."""
