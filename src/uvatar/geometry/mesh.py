"""The counts shared by every triangle-mesh container (:class:`uvatar.capture.types.TexturedMesh`,
:class:`uvatar.body.base.BodyTemplate`): one home for ``num_vertices`` / ``num_faces``."""

from __future__ import annotations

__all__ = ["MeshCounts"]


class MeshCounts:
    """Mixin for a (data)class with ``vertices`` (V, 3) and ``faces`` (F, 3) arrays."""

    __slots__ = ()

    @property
    def num_vertices(self) -> int:
        """V (rows of ``vertices``)."""
        return len(self.vertices)

    @property
    def num_faces(self) -> int:
        """F (rows of ``faces``)."""
        return len(self.faces)
