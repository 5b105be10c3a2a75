"""Model definitions: each module builds one family of solids with gmsh.

A builder returns a :class:`pmask.meshes.common.ModelMesh`: the tetrahedral mesh plus
the default fixed (support) region, contact region and material of the model.
"""
