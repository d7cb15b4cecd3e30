"""How each discovery candidate is hidden in simulated data to test discovery (a test fixture,
shared with ``benchmarks/discovery_confusion.py``).

Each entry is (simulator effects, start model).
"""

# How each candidate is hidden in simulated data to test discovery: (simulator effects, start
# model). Effect sizes are the simulator's defaults (speed dependence and hard collisions: the
# line data's Gamma2/Gamma0 and nu_VC) except second_mode, hidden at 1 % (default 0.3 %): at 25
# transients of 4096 samples a 0.3 % mode with tau ratio 0.7 is described as well by a static
# nonlinearity at tau ratio 1/2. window_history is hidden by starting from a model with H but
# the letter's window.
HIDDEN_CASES = {
    "transfer_function": ({"transfer_function": {}}, None),
    "window_history": ({"transfer_function": {}}, "transfer_function"),
    "static_nonlinearity": ({"static_nonlinearity": {}}, None),
    "extinction_tail": ({"extinction_tail": {}}, None),
    "second_mode": ({"second_mode": {"fraction": 1e-2}}, None),
    "baseline_drift": ({"baseline_drift": {}}, None),
    "mode_beating": ({"mode_beating": {}}, None),
    "speed_dependence": ({"speed_dependence": {}}, None),
    "hard_collisions": ({"hard_collisions": {}}, None),
    "etalon": ({"etalon": {}}, None),
    "neighbour_line": ({"neighbour_line": {}}, None),
}
