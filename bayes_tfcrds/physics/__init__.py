"""The physics of the experiment as pure, vectorised functions.

The transfer function H(f) (letter Eq. 2), the detection chain as a rational filter, the ring-down
forward model IFFT(FFT(S_ed) H) (Appendix A), exponential sums for the fast exact path, line shapes,
line data, and the temperature dependence of a line intensity (partition function Q(T), S(T)).

May import: core.
"""
