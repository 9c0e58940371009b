"""The term language: units, the parser, lowering and compiler of force-law terms into programs, and the
contact kinematics every term reads (below the kernels that run the programs, docs/architecture.md, Layers).

``afmid.terms.expr`` is the facade over ``term_parser``, ``term_units``, ``term_lowering``, ``term_compile``.
"""
