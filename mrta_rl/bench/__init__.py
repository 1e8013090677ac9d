"""Benchmarks: env and learner throughput, the threaded env they measure, a neural run profile."""
