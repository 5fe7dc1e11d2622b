"""Recording human demonstrations: fly a scenario with a joystick or the keyboard (issue 8).

- ``config``: the stick/keyboard mapping, ``scenarios/NAME/recorder.yaml`` (optional);
- ``flight``: ``Recorder``, the flight one held input sample at a time (no window);
- ``save``: a valid flight -> ``demos/recorded_NN.csv`` + an entry in the scenario's demo list;
- ``draw``, ``app``: the pygame window (imported only when a window is needed);
- ``commands``: ``python -m pipeline record`` and ``replay``.
"""
