"""Type stubs of the extension module (see `nerfjit/__init__.py`)."""

from os import PathLike
from typing import Optional, Sequence, Union

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
    def vjp(
        self, name: str, points: npt.ArrayLike, cotangent: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], dict[str, npt.NDArray[np.float32]]]:
        """(values, d_points, d_params): the vector-Jacobian product with `cotangent` (the values' shape)."""

def run(
    script: str,
    *,
    set: Sequence[str] = ...,
    out: Optional[Union[str, PathLike[str]]] = ...,
    resume: bool = ...,
) -> None:
    """Runs the script's blocks as `nerfjit run` does; Ctrl-C stops training with its checkpoint kept."""
