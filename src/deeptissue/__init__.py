"""deeptissue: MRI of an indentation experiment to animal-specific FE models of deep tissue strain.

Modules follow the pipeline and import downward only: io and elements; imaging, scanner, phantom,
segment, contours; pose; geometry, mesh, model; strain; fem (material, contact, solver); errorest,
summary, adapt, study, report; verification and convergence on top. Each module's docstring says
what it holds. Units: mm, N, MPa, s inside the solver; names carry units where a number has one.
"""

__version__ = "0.1.0"
