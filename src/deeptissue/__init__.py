"""deeptissue: MRI of an indentation experiment to animal-specific FE models of deep tissue strain.

Modules follow the pipeline: imaging, phantom, segment, contours, pose, geometry, mesh,
fem (material, contact, solver), strain, report. Units: mm, N, MPa, s inside the solver;
names carry units where a number has one.
"""

__version__ = "0.1.0"
