"""Where the package finds the files it ships with (the repository it was installed from)."""

from __future__ import annotations

import os
from pathlib import Path

# HIFAR_HOME lets an installed copy point at a checkout; otherwise the package sits in one.
REPO_ROOT = Path(os.environ.get("HIFAR_HOME", Path(__file__).resolve().parents[1]))
ASSETS_DIR = REPO_ROOT / "assets"
T1_DIR = ASSETS_DIR / "t1"
SCENE_XML = T1_DIR / "scene.xml"
