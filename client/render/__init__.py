"""The headless render client: a reference renderer (docs/RENDERING.md).

- :mod:`client.render.gl`: EGL context, reversed-Z float depth, GL error checks;
- :mod:`client.render.camera`: poses, the float64 local origin and its rebasing, matrices;
- :mod:`client.render.terrain_mesh`: the full-resolution terrain mesh layer;
- :mod:`client.render.entities`: entity meshes at their poses;
- :mod:`client.render.shading`: sun, colours, fog and sky shared by the layers;
- :mod:`client.render.renderer`: :class:`Renderer`, a frame into a numpy image.

``sortie render`` and ``sortie view`` (client/render_cli.py) drive it.
"""
