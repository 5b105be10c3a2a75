"""Offline half: meshing, FEM assembly, condensation to boundary Green's functions, artifact writer."""
