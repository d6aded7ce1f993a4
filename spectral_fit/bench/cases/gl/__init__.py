"""The paper's two-pass pipeline in OpenGL (moderngl, headless EGL): the speed baseline.

See :mod:`spectral_fit.bench.cases.gl.baseline` and docs/benchmark.md. Importing this package
does not import moderngl; :func:`create_context` does (and raises :class:`GLUnavailable` with
a one-line message when moderngl or EGL is missing).
"""

from .baseline import (
    MAX_SENDERS,
    BaselineInputs,
    GLBaseline,
    GLUnavailable,
    baseline_inputs,
    create_context,
)

__all__ = ["MAX_SENDERS", "BaselineInputs", "GLBaseline", "GLUnavailable", "baseline_inputs",
           "create_context"]
