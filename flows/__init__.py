"""Prefect flows: orchestration only; every task is a thin wrapper over an m3t library function."""
import m3t  # noqa: E402,F401  M3T_REPRODUCIBLE (m3t.arithmetic) applies before any library loads
