"""Declarative studies, the coverage study and the demo.

A TOML file per study, one module per study kind and the registry that runs them; the
simulation-based coverage study; and the demo (the main job).

May import: every layer below the CLI.
"""
