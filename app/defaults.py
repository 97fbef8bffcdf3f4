"""Default file locations the command line falls back on (the files shipped in static/)."""

from __future__ import annotations

from pathlib import Path

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
LIBRARY_PATH = STATIC_DIR / "demos_default.npz"
MODEL_PATH = STATIC_DIR / "model_default.npz"
RESULTS_DIR = STATIC_DIR.parent / "results"
MODELS_DIR = Path("models")  # relative to the working directory: where `train` writes by default
DB_URL = "sqlite:///knotlab.db"
LEVELS: tuple[str, ...] = ("main", "hard")


def task_set_path(level: str, split: str) -> Path:
    """The shipped task set of one perturbation level and split, e.g. tasks_main_test.npz."""
    return STATIC_DIR / f"tasks_{level}_{split}.npz"
