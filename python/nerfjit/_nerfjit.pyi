"""Type stubs of the extension module (see `nerfjit/__init__.py`)."""

from os import PathLike
from pathlib import Path
from typing import Any, Iterator, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

class ScriptError(ValueError):
    """A script that does not compile; the message is the diagnostic: line, column, caret and hint."""

class NerfjitError(RuntimeError):
    """Anything else nerfjit refuses or fails at: a missing file, a bad argument, a run that failed."""

class Script:
    """A compiled `.sdf` script: a path, an example's name or the script's text, with `set` overrides."""

    def __init__(self, source: str, set: Sequence[str] = ...) -> None: ...
    @property
    def functions(self) -> list[str]:
        """The script's own functions' signatures, e.g. `["fn sdf(p: vec3) -> f32"]`."""
    @property
    def params(self) -> dict[str, npt.NDArray[np.float32]]:
        """The params by name (copies; set them with `set_param`)."""
    def set_param(self, name: str, value: npt.ArrayLike) -> None:
        """Sets param `name` to `value` (its shape or its number of values; finite)."""
    def eval(self, name: str, points: npt.ArrayLike) -> npt.NDArray[np.float32]:
        """Function `name` at `points` (N, k): (N,) for an `f32` result, else (N, outputs)."""
    def grad(self, name: str, points: npt.ArrayLike) -> npt.NDArray[np.float32]:
        """Its gradient in the inputs: (N, k) for an `f32` result, else the Jacobian (N, outputs, k)."""
    def mesh(
        self,
        function: str = "sdf",
        resolution: int = 128,
        bounds: Union[float, tuple[Sequence[float], Sequence[float]]] = 1.0,
        level: float = 0.0,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32]]:
        """The marching-cubes mesh of a level set: (vertices (V, 3), faces (F, 3)), faces counter-clockwise."""
    def vjp(
        self, name: str, points: npt.ArrayLike, cotangent: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], dict[str, npt.NDArray[np.float32]]]:
        """(values, d_points, d_params): the vector-Jacobian product with `cotangent` (the values' shape)."""
    def vjp_backward(
        self, name: str, points: npt.ArrayLike, cotangent: npt.ArrayLike, d_points_cotangent: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], dict[str, npt.NDArray[np.float32]]]:
        """(d_points, d_cotangent, d_params): derivatives of w·d_points (vjp's) in its three arguments."""

class Field:
    """A trained field (a checkpoint, or a script with its initial params) that renders into numpy images."""

    @property
    def script(self) -> Script:
        """Its script with the trained params."""
    @property
    def params(self) -> dict[str, npt.NDArray[np.float32]]:
        """The trained params by name."""
    @property
    def rendering(self) -> tuple[float, float, int, list[float]]:
        """(near, far, samples, background) it renders with."""
    def render(
        self,
        c2w: npt.ArrayLike,
        focal: Union[float, tuple[float, float]],
        size: Union[int, tuple[int, int]],
        principal: Optional[tuple[float, float]] = None,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """(image (H, W, 3), depth (H, W), opacity (H, W)) seen by an OpenGL/Blender camera-to-world c2w."""

def load(
    source: str,
    *,
    near: Optional[float] = ...,
    far: Optional[float] = ...,
    samples: Optional[int] = ...,
    background: Optional[str] = ...,
    exact: bool = ...,
) -> Field:
    """Opens a checkpoint (or a script) as a field; the settings override what its train block renders with."""

class Bake:
    """A baked scene: the Gaussian splats of a `.bake` file, drawn by nerfjit's CPU splat renderer."""

    def __init__(self, path: Union[str, PathLike[str]]) -> None:
        """Opens a `.bake` file."""
    def __len__(self) -> int:
        """How many splats it holds."""
    @property
    def background(self) -> list[float]:
        """The color its views are drawn on."""
    @property
    def baked_from(self) -> Path:
        """The checkpoint (or script) it was baked from."""
    @property
    def splats(self) -> dict[str, npt.NDArray[np.float32]]:
        """positions (N, 3), colors (N, 3), opacities (N,), scales (N, 3), rotations (N, 4) and sh (N, 3, 3)."""
    def render(
        self,
        c2w: npt.ArrayLike,
        focal: Union[float, tuple[float, float]],
        size: Union[int, tuple[int, int]],
        principal: Optional[tuple[float, float]] = None,
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """(image (H, W, 3), depth (H, W), opacity (H, W)) seen by an OpenGL/Blender camera-to-world c2w."""

def bake(
    source: str,
    out: Union[str, PathLike[str]],
    *,
    tune: float = ...,
    size: Optional[int] = ...,
    sh_degree: int = ...,
    min_weight: float = ...,
    min_opacity: float = ...,
) -> tuple[Bake, str]:
    """Bakes a checkpoint (or a script) into splats written to `out` as `nerfjit bake` does: (bake, report)."""

def load_views(
    path: str,
    *,
    format: Optional[str] = ...,
    width: Optional[int] = ...,
    background: Optional[str] = ...,
) -> dict:
    """The views of a data set as numpy arrays (see `nerfjit.data.load`)."""

class Trainer:
    """A script's run whose training is followed step by step (`nerfjit.Trainer` wraps it)."""

    def __init__(
        self,
        script: str,
        *,
        set: Sequence[str] = ...,
        out: Optional[Union[str, PathLike[str]]] = ...,
        resume: bool = ...,
    ) -> None: ...
    def steps(self, every: int = 100) -> Steps:
        """Starts the run; iterates over the metrics of every `every`-th training step and the last."""

class Steps(Iterator[dict[str, Any]]):
    """The metrics of a running training, step by step; Ctrl-C or leaving the loop stops it."""

    def __iter__(self) -> Steps: ...
    def __next__(self) -> dict[str, Any]: ...
    def stop(self) -> None:
        """Asks the training to stop at the end of its step, without waiting."""
    def close(self) -> None:
        """Stops the training at the end of its step and waits for it, its checkpoint written."""

def run(
    script: str,
    *,
    set: Sequence[str] = ...,
    out: Optional[Union[str, PathLike[str]]] = ...,
    resume: bool = ...,
) -> None:
    """Runs the script's blocks as `nerfjit run` does; Ctrl-C stops training with its checkpoint kept."""
