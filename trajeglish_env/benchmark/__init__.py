"""Benchmarks: deterministic workloads (:mod:`workloads`), the measurements (:mod:`measure`) and the
suite behind ``trajeglish bench`` (:mod:`suite`). Speed figures come from here, never from unit tests."""
