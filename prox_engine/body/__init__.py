"""Body models: anny (free, embedded, the default) and SMPL-X (the user's licensed files)."""
from __future__ import annotations

from ..config import BODY_MODELS, FitConfig
from ..errors import InputError
from .base import BodyModel


def load_body(config: FitConfig, gender: str | None = None) -> BodyModel:
    """The body model a configuration names (``model``, ``model_path``, ``gender``,
    ``hand_pca``, ``body_segments``, ``vposer_path``); ``gender`` overrides the
    configuration's."""
    if config.model == "anny":
        from .anny_body import AnnyBody

        return AnnyBody.load()
    if config.model == "smplx":
        from .smplx_body import SMPLXBody

        if not config.model_path:
            raise InputError("model_path", "SMPL-X needs the folder of your licensed model "
                                           "files (--model-path DIR or model_path:)")
        return SMPLXBody.load(config.model_path, gender or config.gender, config.hand_pca,
                              config.body_segments, config.vposer_path)
    raise InputError("model", f"unknown body model '{config.model}' (choose "
                              f"{' or '.join(BODY_MODELS)})")
