"""Parts of ``benchmarks.bench_service``: inputs, server, load generator, raw baseline, report."""
