"""The simulator of the whole experiment.

Campaigns of ring-downs, beat notes and CMDS with a known truth and injectable effects.

May import: core, bundle, physics.
"""
