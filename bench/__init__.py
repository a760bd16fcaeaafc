"""Benchmarks: ``sortie bench <suite> [--quick] --json PATH``.

Each suite is a module ``bench.<suite>`` with ``run(quick: bool) -> Report``.
Speed is measured as ratios against a baseline in the same run where
possible, since machines are shared and noisy. Tests never time anything.
"""
