"""The mechanics stage solved per mode (:mod:`ffcomp.compensate.modal_fbs`) against the coupled
three-tower solve: the same spline values, on both bench profiles' centre kernels."""

from pathlib import Path

import numpy as np
import pytest

from ffcomp.compensate.inverse import InverseConfig
from ffcomp.compensate.kernels import mech_kernels, mech_tail_samples
from ffcomp.compensate.modal_fbs import MODES, ModalFbs, modal_split
from ffcomp.compensate.stream import FbsStream
from ffcomp.compensate.stream_inverse import StreamingInverse
from ffcomp.kinematics import inverse
from ffcomp.model.lpv import LpvModel
from ffcomp.profile import default_profile, load_profile

OTHER = Path(__file__).resolve().parents[1] / "samples" / "profiles" / "other_delta.toml"


def _mech(profile):
    model = LpvModel.from_profile(profile)
    si = StreamingInverse(model, 1e-3, InverseConfig())
    x0 = np.array([0.0, 0.0, 0.03])
    si._start(inverse(model.geometry, x0[None])[0], x0)
    return si


@pytest.mark.parametrize("which", ["default", "other"])
def test_the_modal_solve_equals_the_coupled_one(which):
    si = _mech(default_profile() if which == "default" else load_profile(OTHER))
    assert isinstance(si.mech, ModalFbs)  # the centre kernel of both profiles splits
    cfg = InverseConfig()
    win, adv = si.mech.common.W, si.mech.common.A
    # the coupled solve on the model's own kernel, built as StreamingInverse._start builds it
    mats0 = si.model.matrices(si.x_centre[None], check=False)
    L = si.basis.support + mech_tail_samples(mats0, si.dt, cfg.kernel_tol)
    K = mech_kernels(mats0, si.basis, L, cfg.substeps)[0]
    coupled = FbsStream(K, si.basis, win, adv, cfg.reg, cfg.row_stride)
    modal = ModalFbs(*si.mech.kernels, si.basis, win, adv, cfg.reg, cfg.row_stride)
    assert modal.common.lam == pytest.approx(coupled.lam, rel=1e-12)
    rng = np.random.default_rng(7)
    n = 3 * win + 137  # several windows and a short last one
    t = np.arange(n) * 1e-3
    tgt = np.stack([np.sin(2 * np.pi * f * t + p) for f, p in ((3.0, 0.1), (7.0, 1.0), (11.0, 2.0))], 1) * 1e-3
    tgt += 1e-5 * rng.standard_normal(tgt.shape)
    outs = []
    for s in (coupled, modal):
        parts = [s.feed(tgt[i:i + 700]) for i in range(0, n, 700)] + [s.finish()]
        outs.append(np.concatenate(parts))
    assert outs[0].shape == outs[1].shape == (n, 3)
    scale = np.abs(outs[0]).max()
    np.testing.assert_allclose(outs[1], outs[0], atol=1e-9 * scale)


def test_a_kernel_with_unlike_towers_stays_coupled():
    si = _mech(default_profile())
    kc, kd = si.mech.kernels
    K = np.einsum("l,ai,aj->ilj", kc, MODES[:1], MODES[:1]) + np.einsum("l,ai,aj->ilj", kd, MODES[1:], MODES[1:])
    got = modal_split(K)
    assert got is not None
    np.testing.assert_allclose(got[0], kc, atol=1e-15)
    np.testing.assert_allclose(got[1], kd, atol=1e-15)
    K2 = K.copy()
    K2[0, :, 0] *= 1.01  # one tower's own response 1 % stronger
    assert modal_split(K2) is None
    assert modal_split(K[:2]) is None


@pytest.mark.parametrize("which", ["default", "other"])
def test_a_finished_stream_is_freed_without_the_cyclic_collector(which):
    """The CLI makes the cyclic collector's oldest generation all but never run (the parser's and the
    planners' millions of short-lived records): a finished stream must go by reference counting
    alone.  The modal solve's weight used to be a bound method of the solve its two streams hold, a
    cycle: a file with a stop at every retraction kept every stream's solves (5 MB each; 1.5 GB peak
    on a 20 mm cube with 260 G10/G11 as stops, 220 MB now)."""
    import gc
    import weakref

    prof = default_profile() if which == "default" else load_profile(OTHER)
    model = LpvModel.from_profile(prof)
    X = np.zeros((300, 3))
    X[:, 0] = np.linspace(0.0, 0.01, 300)
    X[:, 2] = 0.01
    q = inverse(model.geometry, X)
    was = gc.isenabled()
    gc.disable()
    try:
        inv = StreamingInverse(model, 1e-3, InverseConfig(), keep_padding=True)
        inv.push(q, X)
        inv.finish()
        refs = [weakref.ref(o) for o in (inv, inv.mech, *inv.drive)]
        if isinstance(inv.mech, ModalFbs):
            refs += [weakref.ref(inv.mech.common), weakref.ref(inv.mech.diff)]
        del inv
        assert all(r() is None for r in refs)
    finally:
        if was:
            gc.enable()
