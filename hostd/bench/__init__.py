"""Benchmarks: what accuracy costs in time, and what each part of hostd costs."""
