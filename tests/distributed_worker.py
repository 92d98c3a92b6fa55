"""One process of the loopback multi-process runs of tests/test_distributed.py (not a test module).

``python distributed_worker.py PORT NUM_PROCESSES PROCESS_ID DESIGN OUT [KILL]``: joins the
`jax.distributed` run on 127.0.0.1:PORT (CPU, gloo; XLA_FLAGS gives the host devices),
runs `study_and_tuning` over the global mesh of every process's devices and writes what
*this* process received to ``OUT`` (.npz). With KILL (a process id), that process kills
itself (SIGKILL) after the run and the others run the study again: each must stop with
`fojax.DistributedError`, written to ``OUT.error``.
"""

import collections
import os
import signal
import sys

import jax


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_cpu_collectives_implementation", "gloo")

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import fojax  # noqa: E402
from fojax import studies as S, tuning  # noqa: E402


SIGNALS = ("z1", "z2", "f1", "f2", "f3")
TRACES = collections.Counter()


def studies():
    """Evaluation (7 samples: padded on 2, 3 or 4 devices) and training (2 x 3) studies
    of the §3.3.7 plant with a constant δ, faults and a sine input."""
    ex = fojax.models.example_3_3_7()
    dA = np.zeros((1, 9, 9))
    dA[0, :6, :6] = ex.dA
    plant = fojax.UncertainDescriptorSystem(ex.augmented, dA=dA, delta=fojax.Constant(jnp.zeros(1)))
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


def study_and_tuning(design, devices, loss_devices, steps=3):
    """Metrics and quantile bands of the evaluation study, and `steps` Adam steps of the
    tuning parameters (`fojax.tuning.initial_parameters`, the loss `study_loss` that `tune`
    differentiates, spread over `loss_devices`) on the training study: losses, gradients and final
    parameters, as a flat dict of NumPy arrays."""
    import equinox as eqx
    import optax

    from fojax.studies._runner import SimConfig
    from fojax.studies._sharding import replicate

    ev, train = studies()
    res = S.run_study(ev, design.observer, devices=devices, quantiles=(0.1, 0.5, 0.9), quiet=True)
    out = {f"metric:{k}": np.asarray(v) for k, v in res.metrics.items()}
    cfg = SimConfig(devices=None if loss_devices is None else tuple(loss_devices))
    fx, params = tuning.initial_parameters(design)
    opt = optax.adam(1e-2)

    @eqx.filter_jit
    def step(params, state):
        TRACES["step"] += 1
        loss, grads = eqx.filter_value_and_grad(
            lambda p: S.study_loss(train, tuning.observer_from_parameters(fx, p)[0], cfg=cfg))(params)
        updates, state = opt.update(grads, state, params)
        return loss, grads, optax.apply_updates(params, updates), state

    state = opt.init(params)
    params, state = replicate((params, state), None if loss_devices is None else tuple(loss_devices))
    losses = []
    for k in range(steps):
        loss, grads, params, state = step(params, state)
        losses.append(np.asarray(loss))
        out.update({f"grad{k}:{name}": np.asarray(v) for name, v in grads.items()})
    out["train_loss"] = np.asarray(losses)
    out.update({f"param:{k}": np.asarray(v) for k, v in params.items()})
    out["step_traces"] = np.asarray(TRACES["step"])  # 1: new parameters never recompile
    out["engine"] = np.asarray(res.attrs["engine"])
    out["num_devices"] = np.asarray(res.attrs["num_devices"])
    return out


def main(port, n, pid, design_path, out_path, kill=None):
    jax.distributed.initialize(f"127.0.0.1:{port}", int(n), int(pid), initialization_timeout=60,
                               heartbeat_timeout_seconds=10, shutdown_timeout_seconds=10)
    design = fojax.load_design(design_path)
    out = study_and_tuning(design, jax.devices(), jax.devices())
    out["process_count"] = np.asarray(jax.process_count())
    out["local_devices"] = np.asarray(len(jax.local_devices()))
    np.savez(out_path, **out)
    if kill is None:
        return 0
    if int(pid) == int(kill):
        os.kill(os.getpid(), signal.SIGKILL)
    ev, _ = studies()
    try:
        S.run_study(ev, design.observer, devices=jax.devices(), quantiles=(), quiet=True)
    except fojax.DistributedError as err:
        with open(out_path + ".error", "w") as f:
            f.write(str(err))
        sys.stdout.flush()
        os._exit(0)  # skip jax.distributed's shutdown barrier, which the dead process cannot join
    return 5  # no error although a process was killed


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
