"""Benchmarks that print ratios against peers or baselines measured in the same run (`a3cqp bench NAME`)."""
