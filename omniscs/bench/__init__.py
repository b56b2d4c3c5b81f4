"""Benchmarks, one package and one harness: each runs the real pipeline stages and writes reports/<name>.*"""
