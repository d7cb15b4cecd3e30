"""The physics of the experiment as pure, vectorised functions.

The transfer function H(f) (letter Eq. 2), the detection chain as a rational filter, the ring-down
forward model IFFT(FFT(S_ed) H) (Appendix A), exponential sums for the fast exact path, line shapes
and line data.

May import: core.
"""
