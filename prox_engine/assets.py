"""Where generated assets live, and the one-time set-up that makes them.

anny's first build takes about a minute, peaks at 1.4 GB and writes ~0.8 GB of cache, so
``prox setup`` (run by ``make setup``) builds it once, bakes the float32 model data to a
safetensors file, and warms warp's kernel cache (skinning, bone chain, nearest faces) and
numba's (L-BFGS's directions); run time only loads that file.
"""
from __future__ import annotations

import contextlib
import functools
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path


def home() -> Path:
    """Root of generated data: ``$PROX_HOME``, default ``~/.cache/prox``."""
    return Path(os.environ.get("PROX_HOME", Path.home() / ".cache" / "prox")).absolute()


def anny_model_path() -> Path:
    return home() / "anny-0.6.2-default-float32.safetensors"


def sdf_cache_dir() -> Path:
    return home() / "sdf"


@functools.cache
def configure_warp() -> None:
    """Point warp at our kernel cache and start it quietly, once per process; must run
    before anny (and so warp) is imported. Without this every command and worker log would
    begin with warp's device banner and, on machines without a GPU, a CUDA warning its C
    code prints."""
    os.environ.setdefault("WARP_CACHE_PATH", str(home() / "warp"))
    import warp

    warp.config.log_level = warp.LOG_WARNING
    with _stderr_silenced():
        warp.init()  # a no-op once warp has started


@contextlib.contextmanager
def _stderr_silenced() -> Iterator[None]:
    """Discard what native code writes to file descriptor 2 meanwhile."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def setup(force: bool = False, say: Callable[[str], None] = lambda _: None) -> Path:
    """Bake the anny model data (if missing) and warm the warp kernel cache, telling
    ``say`` what it is doing."""
    configure_warp()
    target = anny_model_path()
    if force or not target.exists():
        say("building anny's body model from its MakeHuman data (once, about 80 s) ...")
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
    import numpy as np
    import torch

    from .body.anny_body import AnnyBody
    from .camera import Camera
    from .contact_distance import ContactDistance
    from .geometry import VertexNormals
    from .inside_depth import InsideDepth
    from .keypoint_terms import posed_terms
    from .lbfgs import compile_directions
    from .nearest_face import nearest_faces
    from .rigid_terms import rigid_fit
    from .sample_grid import SampleGrid
    from .scene_sdf import surface_tree
    from .trilinear import Trilinear

    say("compiling the warp kernels: skinning, bone chain, keypoints and their terms, the "
        "start search's rigid fit, nearest samples and faces, SDF reads, depths inside, "
        "contact distances, normals, and numba's L-BFGS directions (cached after the first "
        "time) ...")
    body = AnnyBody.load()
    params = {k: v.requires_grad_(True) for k, v in body.init_params(1).items()}
    out = body(params)  # skinning, bone chain and anchored keypoints, both ways
    up = torch.tensor([0.0, -1.0, 0.0])
    (out.vertices.sum() + sum(posed_terms(  # every keypoint term: one kernel
        out.keypoints, Camera(1.0, 1.0, 0.0, 0.0), torch.zeros(1, out.keypoints.shape[1], 2),
        torch.ones(1, out.keypoints.shape[1]), 1.0, up, 1.0, 1.0, torch.ones(1, 2))).sum()
     ).backward()
    one = torch.ones(1)
    rigid_fit(torch.zeros(1, 3), torch.ones(1, 3), torch.eye(3)[None], torch.zeros(1, 1, 3),
              Camera(1.0, 1.0, 0.0, 0.0), torch.zeros(1, 1, 2), one[None], one[None], one, one,
              up, up, 1.0, 1.0, 1.0)
    samples = np.eye(3)
    grid = SampleGrid.build(samples, surface_tree(samples))
    grid.query(np.zeros((1, 3)), 1)
    triangle = torch.eye(3, dtype=torch.float64)[None]
    nearest_faces(torch.zeros(1, 3, dtype=torch.float64), torch.zeros(1, 1, dtype=torch.int64),
                  triangle, triangle[:, 0])
    reader = Trilinear(torch.zeros(2, 2, 2), torch.zeros(3), torch.ones(3))
    reader(torch.zeros(1, 3, requires_grad=True))
    InsideDepth(reader, torch.eye(4), grid, torch.zeros(3, dtype=torch.int64), triangle,
                triangle[:, 0], 1)(torch.zeros(1, 3), (-1.0, 1.0))
    ContactDistance(reader, reader, torch.eye(4), 0.1)(torch.zeros(1, 1, 3),
                                                      torch.ones(1, 1, 3), 1.0, 0.0)
    VertexNormals(body.faces, torch.zeros(1, dtype=torch.long))(
        torch.zeros(1, body.num_vertices, 3))
    compile_directions()  # and numba's, of L-BFGS's directions
    return target
