"""Where generated assets live, and the one-time set-up that makes them.

anny's first build takes about a minute, peaks at 1.4 GB and writes ~0.8 GB of cache, so
``prox setup`` (run by ``make setup``) builds it once, bakes the float32 model data to a
safetensors file, and warms warp's kernel cache; run time only loads that file.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path


def home() -> Path:
    """Root of generated data: ``$PROX_HOME``, default ``~/.cache/prox``."""
    return Path(os.environ.get("PROX_HOME", Path.home() / ".cache" / "prox")).absolute()


def anny_model_path() -> Path:
    return home() / "anny-0.6.2-default-float32.safetensors"


def sdf_cache_dir() -> Path:
    return home() / "sdf"


def configure_warp() -> None:
    """Point warp at our kernel cache; must run before anny (and so warp) is imported."""
    os.environ.setdefault("WARP_CACHE_PATH", str(home() / "warp"))


def setup(force: bool = False) -> Path:
    """Bake the anny model data (if missing) and warm the warp kernel cache."""
    configure_warp()
    target = anny_model_path()
    if force or not target.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
        build_dir = Path(tempfile.mkdtemp(prefix="anny-build-", dir=target.parent))
        os.environ["ANNY_CACHE_DIR"] = str(build_dir)  # never touch the user's ~/.cache/anny
        try:
            import anny
            import torch

            model = anny.Anny().to(torch.float32)
            tmp = target.with_name(target.name + ".tmp")
            model.to_model_data().save_safetensors(str(tmp))
            os.replace(tmp, target)
        finally:
            shutil.rmtree(build_dir, ignore_errors=True)
    from .body.anny_body import AnnyBody

    body = AnnyBody.load()  # compiles and caches the skinning kernel
    body(body.init_params(1))
    return target
