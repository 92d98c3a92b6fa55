"""One process of the loopback multi-process runs of tests/test_distributed.py (not a test module).

``python distributed_worker.py PORT NUM_PROCESSES PROCESS_ID DESIGN OUT [KILL WHEN]``: joins the
`jax.distributed` run on 127.0.0.1:PORT (CPU, gloo; XLA_FLAGS gives the host devices),
runs `study_and_tuning` over the global mesh of every process's devices (its tuning
checkpoint at ``OUT.ckpt/tune``: a path of its own) and writes what *this* process
received to ``OUT`` (.npz). With KILL (a process id), that process kills itself (SIGKILL)
while every process runs the study again (WHEN ``run_study``: right before it) or tunes
again (``tune``: after the first of two steps); every other process must stop with
`fojax.errors.DistributedError`, whose message goes to ``OUT.error``. (Only the first collective
after the death can raise it: the heartbeat, 10 s here, ends a process that JAX finds
waiting for the dead one, with JAX's own message.)
"""

import faulthandler
import os
import signal
import sys

import jax


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_cpu_collectives_implementation", "gloo")

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from helpers import uncertain_plant_3_3_7  # noqa: E402

import fojax  # noqa: E402
from fojax import studies as S, tuning  # noqa: E402


SIGNALS = ("z1", "z2", "f1", "f2", "f3")


def studies():
    """Evaluation (7 samples: padded on 2, 3 or 4 devices) and training (2 x 3) studies
    of the §3.3.7 plant with a constant δ, faults and a sine input."""
    ex = fojax.models.example_3_3_7()
    plant = uncertain_plant_3_3_7(ex)
    x0 = jnp.zeros(9).at[:4].set(jnp.array([1.0, -0.5, 0.5, 0.2]))
    u = fojax.Sine(jnp.array([1.0, 0.5]), jnp.array([1.0, 2.0]))
    ts = jnp.linspace(0.0, 1.0, 21)
    k1, k2, k3, k4 = jax.random.split(jax.random.PRNGKey(3), 4)

    def study(kd, kf, nu, nf, u=u):
        return S.Study(plant, x0, ts, ex.L_aug, u, uncertainty=(S.constant_delta(kd, nu, 1, bounds=(-1.0, 1.0)),),
                       scenarios=(S.constant_faults(kf, nf, x0, 3),), signal_names=SIGNALS)

    # evaluation: the input also steps between grid points (t = 0.37: the exact engine's jumps)
    evaluation = study(k1, k2, 7, 1, u=u + fojax.Step(jnp.array([0.5, -0.3]), 0.37))
    return evaluation, study(k3, k4, 2, 3)


def time_varying_study():
    """5 samples of a sinusoidal δ(t) (the exponential engine of `run_study`)."""
    ex = fojax.models.example_3_3_7()
    plant = uncertain_plant_3_3_7(ex)
    x0 = jnp.zeros(9).at[:4].set(jnp.array([1.0, -0.5, 0.5, 0.2]))
    return S.Study(plant, x0, jnp.linspace(0.0, 1.0, 21), ex.L_aug, fojax.Sine(jnp.array([1.0, 0.5]), 1.0),
                   uncertainty=(S.sinusoidal_delta(jax.random.PRNGKey(5), 5, 1, amplitude=(0.0, 0.5)),),
                   signal_names=SIGNALS)


def study_and_tuning(design, devices, loss_devices, checkpoint):
    """As a flat dict of NumPy arrays:

    - metrics and quantile bands of the evaluation study (`run_study` over `devices`);
    - its metrics with ``chunk_size=2``: blocks of 2 samples, dealt to the devices
      unevenly (7 samples: on 3 devices 2 + 2 + 2 and then 1);
    - the metrics of `time_varying_study` (exponential engine, ``chunk_size=2``);
    - `fojax.tune` over `loss_devices` on the training study (Adam on the loss
      `study_loss`, spread over `loss_devices`): 1 step with a checkpoint at `checkpoint`,
      then resumed from it to step 2: history (the training losses) and parameters; the
      checkpoint (parameters and Adam's moments, i.e. functions of each step's gradient)
      is compared file for file by the test, and the trace count says whether resuming
      with new parameters compiled again.

    (A hand-written Adam loop of `study_loss` over `loss_devices` was here too. It compiled a
    third gradient program in every process and proved nothing the above does not: its
    losses are `tune`'s ``train_loss``, its gradients enter Adam's moments in the
    checkpoint and the parameters of every process, its one trace is ``tune_traces``; and
    the gradient on several devices is compared with one device bit for bit in-process,
    tests/test_distributed.py::test_study_loss_and_gradient_on_several_devices_equal_one_device.)
    """
    ev, train = studies()
    res = S.run_study(ev, design.observer, devices=devices, quantiles=(0.1, 0.5, 0.9), quiet=True)
    out = {f"metric:{k}": np.asarray(v) for k, v in res.metrics.items()}
    uneven = S.run_study(ev, design.observer, devices=devices, chunk_size=2, quantiles=(0.5,), quiet=True)
    out.update({f"uneven:{k}": np.asarray(v) for k, v in uneven.metrics.items()})
    tv = S.run_study(time_varying_study(), design.observer, devices=devices, chunk_size=2, quantiles=(), quiet=True)
    out.update({f"tv:{k}": np.asarray(v) for k, v in tv.metrics.items()})
    out["tv_engine"] = np.asarray(tv.attrs["engine"])
    for n_steps, resume in ((1, False), (2, True)):
        tr = tuning.tune(design, train, steps=n_steps, checkpoint=checkpoint, resume=resume,
                         devices=None if loss_devices is None else tuple(loss_devices))
    out["tune_loss"] = np.asarray(tr.history["train_loss"])
    out.update({f"tune_param:{i}": np.asarray(a) for i, a in enumerate(jax.tree.leaves(tr.params))})
    out["tune_traces"] = np.asarray(tuning._tune.TRACE_COUNTS["tune_step"])  # the resumed run: no new trace
    out["engine"] = np.asarray(res.attrs["engine"])
    out["num_devices"] = np.asarray(res.attrs["num_devices"])
    return out


def main(port, n, pid, design_path, out_path, kill=None, when=None):
    faulthandler.dump_traceback_later(420, exit=False)  # where a process hangs, in its log
    jax.distributed.initialize(f"127.0.0.1:{port}", int(n), int(pid), initialization_timeout=60,
                               heartbeat_timeout_seconds=10, shutdown_timeout_seconds=10)
    design = fojax.load_design(design_path)
    os.makedirs(out_path + ".ckpt")
    out = study_and_tuning(design, jax.devices(), jax.devices(), os.path.join(out_path + ".ckpt", "tune"))
    out["process_count"] = np.asarray(jax.process_count())
    out["local_devices"] = np.asarray(len(jax.local_devices()))
    np.savez(out_path, **out)
    if kill is None:
        return 0
    killed = int(pid) == int(kill)
    ev, train = studies()

    def die(*_):
        os.kill(os.getpid(), signal.SIGKILL)

    try:
        if when == "run_study":
            if killed:
                die()
            S.run_study(ev, design.observer, devices=jax.devices(), quantiles=(), quiet=True)
        else:  # the step is compiled already (study_and_tuning): step 2 comes within a second
            tuning.tune(design, train, steps=2, devices=jax.devices(), callback=die if killed else None)
    except fojax.errors.DistributedError as err:
        with open(out_path + ".error", "w") as f:
            f.write(str(err))
        sys.stdout.flush()
        os._exit(0)  # skip jax.distributed's shutdown barrier, which the dead process cannot join
    return 5  # no error although a process was killed


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
