"""Pictures: point-cloud / mesh renders and GIFs (matplotlib, no system deps), dataset previews and
the self-contained HTML viewer.

- :mod:`~pocoloco.viz.render`: ``render_grid`` (clouds from several views, coloured by label /
  normal / height), ``render_meshes``, ``plot_curves``, turntable and animation GIFs.
- :mod:`~pocoloco.viz.preview`: ``preview_dataset`` (frames of a dataset, coloured by label).
- :mod:`~pocoloco.viz.viewer`: ``write_viewer`` (one offline WebGL page for a folder of clouds).
"""
