"""Project dashboard over the MLflow store."""
