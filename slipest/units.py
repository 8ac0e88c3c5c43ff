"""Physical constants and unit conversions shared by the whole package.

Everything inside slipest is SI (m, s, kg, N, rad). Accelerations are only
expressed in g at the edges (features such as ``Da`` are reported in g, as
the thesis does); use these helpers to convert.
"""

#: Standard gravity used throughout the model and the log format [m/s^2].
#: The log format documents "+9.81 at rest", so the model uses the same value.
G = 9.81


def to_g(a_mps2):
    """Convert an acceleration from m/s^2 to g (works on scalars and arrays)."""
    return a_mps2 / G


def from_g(a_g):
    """Convert an acceleration from g to m/s^2 (works on scalars and arrays)."""
    return a_g * G
