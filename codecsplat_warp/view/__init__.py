"""``codecsplat view``: the decoded scene in a web browser, served from Python by viser.

* :mod:`.options`: the command's options (argparse only);
* :mod:`.serve`: from the options to a running server (:func:`~.serve.serve`), every input checked first;
* :mod:`.inputs`: a bitstream, a 3DGS PLY or a scene folder (which it encodes) read into a
  :class:`~.inputs.ViewScene`;
* :mod:`.app`: the viewer (:class:`~.app.Viewer`): splats, frustums, the panel, server-rendered frames, re-encoding;
* :mod:`.geometry`: the viewer's world frame, browser cameras as package cameras and pose files, splat arrays;
* :mod:`.ports`: the port check; :mod:`.worker`: the background threads' latest-request queue.

Nothing heavy is imported here: ``codecsplat --help`` reads :mod:`.options` without torch or viser.
"""
