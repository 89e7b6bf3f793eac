"""Training entry points (run from the repository root): ``python -m train.stage1``."""
