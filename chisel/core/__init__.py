"""The base every layer shares: errors, rigid geometry and cameras, atomic writes, ray
casting of meshes and the Mitsuba variant. Imports nothing above it (no ``chisel.io``,
no method module); ``sim`` and ``phantoms`` build on it."""
