"""Prefect flows: the factory's pipelines, composed from tasks."""
