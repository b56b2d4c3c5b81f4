"""Benchmarks, one package and one harness: each runs the real pipeline stages and writes its reports into one
folder, reports/<name>/ (report.json, report.md and its pictures)."""
