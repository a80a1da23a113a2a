"""Data sets as numpy arrays, for people who bring their own training loop.

    views = nerfjit.data.load("fern", width=504)        # LLFF, DTU, COLMAP, nerfstudio, Blender, the course's
    views["images"]      # (N, H, W, 3) float32, composited on the background
    views["c2w"]         # (N, 4, 4) camera-to-world, OpenGL / Blender convention (looking down -z, +y up)
    views["intrinsics"]  # (N, 4) fx, fy, cx, cy in pixels of these images
    views["masks"]       # (N, H, W) bool where the data set has object masks (DTU), else None
    views["read_as"]     # how the path was read, e.g. "read as LLFF (poses_bounds.npy)"

A folder holding several layouts is read as the most specific (DTU, LLFF, nerfstudio, COLMAP, Blender) unless
`format` names one; `path` may also be a reader written as in a script, `'dtu("scan24", masks: true)'`.
Captures are normalized as training normalizes them by default (DTU scans stay in the scan's frame).
"""

from ._nerfjit import load_views


def load(path, *, format=None, width=None, background="black"):
    """The views of the data set at `path` (see the module's docs): every frame, at about `width` pixels
    across (by default at full size; Blender transforms at 128²), composited on `background`."""
    return load_views(str(path), format=format, width=width, background=background)


__all__ = ["load"]
