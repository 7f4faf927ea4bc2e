"""``refsim interactive``: the needle base driven live, by keyboard in a pyvista window or by a pose stream
on a loopback socket (the force sent back every step), recorded to HDF5 with a replay scene beside it
(docs/interactive.md).

Modules: :mod:`~refsim.interactive.pose` (the commanded and applied pose, keys, pose messages),
:mod:`~refsim.interactive.recording` (the applied trajectory, its CSV and the replay scene),
:mod:`~refsim.interactive.session` (the stepped, recorded run), :mod:`~refsim.interactive.pacing` (real time
or lock step), :mod:`~refsim.interactive.server` (the pose stream), :mod:`~refsim.interactive.window`
(pyvista), :mod:`~refsim.interactive.command` (the command line). Importing this package imports none of them.
"""
