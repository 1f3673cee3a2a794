"""Coverage-guided fuzzing of every peer-facing parser (see targets.py and README)."""
