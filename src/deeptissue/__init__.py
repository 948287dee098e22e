"""deeptissue: MRI of an indentation experiment to animal-specific FE models of deep tissue strain.

Modules follow the pipeline and import downward only, as the table ``LAYERS`` in
tests/test_layers.py declares and tests: io, elements, geometry, rigid, variants; imaging, contours,
scanner, qc, fluid, bone_motion; segment; pose; phantom; mesh, strain; fem; errorest, summary, adapt;
model; study; report, findings, verification, convergence; config and status on top. Each module's
docstring says what it holds. Units: mm, N, MPa, s inside the solver; names carry units where a number has one.
"""

__version__ = "0.1.0"
