"""One exception type per kind of fault.

Every message says what was expected and what arrived, and names the argument or file.
All input errors are ``ValueError`` subclasses, so callers that only know the standard
library can still catch them.
"""

from __future__ import annotations


class RoGUENeRFError(Exception):
    """Base class of every error this library raises on purpose."""


class InputError(RoGUENeRFError, ValueError):
    """An argument has the wrong shape, dtype or values (bad pose, fx <= 0, NaN ...)."""


class SceneFormatError(InputError):
    """A scene file is missing or malformed; the message names the file and the problem."""

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class CheckpointError(InputError):
    """A checkpoint is not a valid RoGUENeRF safetensors file, or does not fit the model."""


class NonFiniteOutputError(RoGUENeRFError, RuntimeError):
    """The enhancer produced NaN/inf for an input; the result is never returned or encoded."""


class TrainingDivergedError(RoGUENeRFError, RuntimeError):
    """The training loss became non-finite; the last good checkpoint was kept."""

    def __init__(self, step: int, loss: float, checkpoint: str | None = None):
        self.step = step
        self.loss = loss
        self.checkpoint = checkpoint
        where = f"; last good checkpoint: {checkpoint}" if checkpoint else ""
        super().__init__(f"non-finite training loss ({loss}) at step {step}{where}")


class TrainingCancelled(RoGUENeRFError):
    """Training stopped because its ``should_stop`` callback asked it to."""

    def __init__(self, step: int, checkpoint: str | None = None):
        self.step = step
        self.checkpoint = checkpoint
        super().__init__(f"training cancelled at step {step}")


class CameraMismatchError(InputError):
    """A camera (one view's, or a camera path's) does not fit the scene's world: its pixels land
    nowhere near the training photos' surfaces at their depth (:func:`roguenerf.trajectory.check_camera`,
    :func:`roguenerf.trajectory.check_path`). ``problem`` says what was found and the likely causes,
    ``cause`` names the likeliest: ``"convention"`` (OpenGL vs OpenCV axes), ``"scale"`` (another
    unit), ``"world"`` (another coordinate space), ``"geometry"`` (the field's own depth is off on
    novel views) or ``"depth_type"`` (z vs ray depth); ``override`` is how the caller goes on anyway."""

    def __init__(self, problem: str, cause: str, override: str = "--force (force=True)"):
        self.problem = problem
        self.cause = cause
        self.override = override
        super().__init__(f"{problem}. To enhance it anyway: {override}")


class PathCancelled(RoGUENeRFError):
    """Enhancing a camera path stopped because its ``should_stop`` callback asked it to; the
    frames done so far are kept and a later call resumes after them."""

    def __init__(self, frame: int):
        self.frame = frame
        super().__init__(f"camera path cancelled after {frame} frames")
