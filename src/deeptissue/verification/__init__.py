"""Verification scenes above the FE core: analytical solutions, simple meshes, the material checks,
the Hertz, patch and locking cases, the hard cases on a limb and the cylinder scene. They import
:mod:`deeptissue.fem` and the study layer; nothing below imports them."""
