"""The synthetic lab: depth recordings of the hand model with known truth, and the experiments that
evaluate the tracker on them.

Modules
-------
render
    :class:`~tracker.sim.render.DepthRenderer` / :func:`~tracker.sim.render.render`: the LBS-posed
    hand mesh z-buffered through a pinhole camera (depth, segment labels, colour, incidence), with
    optional :class:`~tracker.sim.clutter.Clutter` (bare or sleeved forearm, torso, table, box or
    cylinder), each clutter element with its own label.
meshes
    The clutter's closed triangle meshes (forearm and sleeve tubes, torso and box superellipsoids, cylinder).
_kernels
    The numba kernels of the renderer and of the sensor noise.
raycast
    A plain numpy ray caster, the independent reference the renderer is tested and benchmarked against.
noise
    :class:`~tracker.sim.noise.NoiseModel`: depth-sensor noise with switchable parts and presets
    (``none``, ``kinect1``, ``sr305`` = ``realsense``, ``d4xx``).
hands
    :class:`~tracker.sim.hands.HandShape`: rendered hands of other sizes and finger proportions than
    the tracking model, and the ``truth_hand.yaml`` a synthetic recording carries.
motions
    θ trajectories: :class:`~tracker.sim.motions.Motion`, global paths, file replay (angle tables,
    schroeder26 posture files) and the named scenarios of ``tracker synth``.
synthesize
    :func:`~tracker.sim.synthesize.synthesize`: motion → rendered, noisy frames → recording folder
    with ``truth.csv``.
experiments
    The paper's experiments (ICP iterations, sampling density, modes, occlusion, single frames,
    scenarios) and realistic scenes (clutter × sensor × hand size) run in memory: render → observe →
    track → posture and keypoint error.
report
    Every experiment run once and written as ``report.md`` with figures.
cli
    The ``tracker synth`` and ``tracker experiments`` commands, registered into the ``tracker`` app.

The dependency runs one way: this package imports the tracking code to evaluate it; the tracking
code never imports this package (only the command-line entry :mod:`tracker.cli` registers the
commands of :mod:`tracker.sim.cli`).
"""
