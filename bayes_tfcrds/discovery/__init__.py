"""Discovery.

Compare a model of the experiment with every data block, try candidate effects as model extensions
and add what the evidence supports; the report and the notebook views.

May import: core, output, bundle, physics, fit.
"""
