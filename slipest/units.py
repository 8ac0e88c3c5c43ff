"""Physical constants shared by the whole package.

Everything inside slipest is SI (m, s, kg, N, rad). Accelerations are only
expressed in g at the edges (features such as ``Da`` are reported in g, as
the thesis does): divide by :data:`G`.
"""

#: Standard gravity used throughout the model and the log format [m/s^2].
#: The log format documents "+9.81 at rest", so the model uses the same value.
G = 9.81
