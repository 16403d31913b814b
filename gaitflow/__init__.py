"""gaitflow: marker-based motion capture and gait analysis with one depth camera.

Conventions shared by every module (each module's docstring repeats the ones it uses):

- images are (row, col) = (v, u) arrays, 512 wide by 424 high for a Kinect v2;
- pixel (u, v) = (column, row), (0, 0) is the centre of the top-left pixel;
- time is axis 0 of any time series;
- NaN means missing and propagates;
- units are mm, s and degrees; capture times on the bus are int64 nanoseconds.
"""

__version__ = "0.1.0"
