"""Prefect flows: orchestration only; every task is a thin wrapper over an m3t library function."""
