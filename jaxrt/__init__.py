"""jaxrt: a JAX array ray tracer for analysing and fitting BRDFs.

Submodules (imported on demand so `import jaxrt` stays cheap):
  mesh, data, bvh        geometry: mesh loading, the data registry, BVH build and traversal
  scene, camera, lights  scene description
  integrators, image     rendering and image I/O
"""

__version__ = "0.1.0"
