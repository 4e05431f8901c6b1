"""Pure unit and time constants shared across the package (no imports, no behaviour).

Time is int64 nanoseconds everywhere; seconds appear only in TUM files and displays.
"""

NS_PER_S = 1_000_000_000  # nanoseconds per second (int, so int64 time arithmetic stays exact)
