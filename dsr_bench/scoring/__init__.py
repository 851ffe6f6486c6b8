"""Scoring: the predictions contract (`predictions`), the benchmark's metrics (`metrics`), the strict
`evaluate` of a predictions directory, and the `leaderboard` built from results.

Imports with numpy and h5py alone.
"""
