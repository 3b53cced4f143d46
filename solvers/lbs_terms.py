"""The incremental potential of one LBS time step, split where it is evaluated (see :mod:`.lbs`).

:class:`ElasticTerms` is the elastic (cubature) part on the simulation's Warp device (one kernel and
torch reductions per evaluation); :class:`HostTerms` the rest — inertia, drags, gravity, the clamp, ground contact
and friction — on the host in float64 numpy over the reduced (3 × nA) unknowns; :class:`CholeskyFactors` the
Newton systems' factors; :func:`host_matmul` and :class:`PhaseClock` the host's small helpers.  Units: SI
(m, s, kg, Pa); state rows Z are (R, 3, nA) handle-space coordinates.
"""

from __future__ import annotations

import time
from typing import Optional

import numpy as np


class PhaseClock:
    """Seconds spent per named phase, accumulated."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds


def host_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b on the host: numpy for tiny products, else torch's CPU BLAS (one thread inside a run).

    numpy's OpenBLAS runs products above ~10⁴ multiply-adds (a 44 × 256 matrix-vector product
    already) on its own thread pool, which stalls for milliseconds on a loaded machine.
    """
    if a.size * b.shape[-1] <= 8192:
        return a @ b
    import torch

    return torch.matmul(torch.from_numpy(np.ascontiguousarray(a)), torch.from_numpy(np.ascontiguousarray(b))).numpy()


class CholeskyFactors:
    """Cholesky factors of R symmetric positive-definite systems A (R, N, N), on the host in float64.

    Only the lower triangle of A is read.  A system whose factorisation fails gets a diagonal shift of
    1e-8 × its largest diagonal entry.
    """

    def __init__(self, A: np.ndarray):
        import torch

        A = np.ascontiguousarray(A)
        L, info = torch.linalg.cholesky_ex(torch.from_numpy(A))
        bad = np.flatnonzero(info.numpy() != 0)
        if len(bad):
            shift = 1e-8 * np.abs(np.diagonal(A[bad], axis1=1, axis2=2)).max(axis=1)
            shifted = A[bad] + shift[:, None, None] * np.eye(A.shape[1])
            L[torch.from_numpy(bad)] = torch.linalg.cholesky_ex(torch.from_numpy(shifted))[0]
        self.L = L

    def subset(self, rows: np.ndarray) -> "CholeskyFactors":
        """The factors of the systems ``rows`` (indices)."""
        import torch

        part = object.__new__(CholeskyFactors)
        part.L = self.L[torch.from_numpy(np.asarray(rows, np.int64))]
        return part

    def solve(self, b: np.ndarray) -> np.ndarray:
        """A⁻¹ b for right-hand sides b (R, ...) with N numbers each."""
        import torch

        rhs = torch.from_numpy(np.ascontiguousarray(b).reshape(len(b), -1, 1))
        return torch.cholesky_solve(rhs, self.L).numpy().reshape(b.shape)


class HostTerms:
    """The incremental potential's terms other than elasticity for one time step, on the host (numpy, float64).

    Inertia w/(2dt²) ‖Z − Ẑ‖²_M (w = 1/β for Newmark, 1 for backward Euler), Rayleigh drag ½ c/dt ‖Z − Z_n‖²_M, quadratic drag ½/dt ‖Z − Z_n‖²_Mq,
    −f_ext·Z, the clamp ½ κ_p ‖Z‖²_Mpin, the ground's spring ½ Σ k_k (h − z_k)₊² and damper
    ½ Σ c_k/dt (z_k − z_k,n)² at the samples in contact, and Coulomb friction Σ μ N_k f0(|Δx_t,k|) (module
    docstring); kc, cc: (E, K) per environment and collision sample.  They reach the handle space only through (nA, nA)
    matrices and the collision points' lifted basis (K, nA), so they cost microseconds and need no
    device round trip.

    Methods take state rows Z (R, 3, nA) and their environments env (R,) (indices into the (E, ...)
    per-environment arrays).
    """

    def __init__(self, *, M, Mpin, kp, dt, Z_hat, Z_start, lin_drag, f_ext, Mq, Hconst, ground, kc, cc, a_col, z_col,
                 N_lag, mu_fric, eps, inertia_weight):
        self.M, self.Mpin, self.kp, self.dt = M, Mpin, kp, dt
        self.inertia_weight = inertia_weight
        self.Z_hat, self.Z_start, self.lin_drag, self.f_ext, self.Mq = Z_hat, Z_start, lin_drag, f_ext, Mq
        self.Hconst, self.ground, self.kc, self.cc, self.a_col, self.z_col = Hconst, ground, kc, cc, a_col, z_col
        self.N_lag, self.mu_fric, self.eps = N_lag, mu_fric, eps
        self.a_col_T = np.ascontiguousarray(a_col.T)
        if ground is not None:
            self.z_start = z_col + host_matmul(Z_start[:, 2, :], self.a_col_T)                  # (E, K) m

    def _friction(self, Z, env):
        """Tangential slips (R, 2, K) m since the step start, f0 (R, K) and f1(y)/y (R, K) (IPC's C¹ smoothing)."""
        eps = self.eps
        ut = host_matmul(Z[:, :2, :] - self.Z_start[env][:, :2, :], self.a_col_T)
        y = np.sqrt(ut[:, 0] ** 2 + ut[:, 1] ** 2)
        slipping = y >= eps
        f0 = np.where(slipping, y, -y ** 3 / (3 * eps ** 2) + y ** 2 / eps + eps / 3)
        f1_over_y = np.where(slipping, 1.0 / np.maximum(y, 1e-300), 2.0 / eps - y / eps ** 2)
        return ut, f0, f1_over_y

    def energy_gradient(self, Z: np.ndarray, env: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Φ without elasticity (R,) J and its gradient (R, 3, nA)."""
        nA = Z.shape[2]
        dt = self.dt
        D = Z - self.Z_hat[env]
        dZ = Z - self.Z_start[env]
        DM = host_matmul(D.reshape(-1, nA), self.M).reshape(D.shape)
        dZM = host_matmul(dZ.reshape(-1, nA), self.M).reshape(D.shape)
        drag = self.lin_drag[env] / dt
        fe = self.f_ext[env]
        w = self.inertia_weight
        phi = (0.5 * w / dt ** 2 * np.einsum("ram,ram->r", DM, D) + 0.5 * drag * np.einsum("ram,ram->r", dZM, dZ)
               - np.einsum("ram,ram->r", fe, Z))
        grad = w / dt ** 2 * DM + drag[:, None, None] * dZM - fe
        if self.Mpin is not None:
            ZP = host_matmul(Z.reshape(-1, nA), self.Mpin).reshape(Z.shape)
            phi += 0.5 * self.kp * np.einsum("ram,ram->r", ZP, Z)
            grad += self.kp * ZP
        if self.Mq is not None:
            dZMq = np.matmul(dZ, self.Mq[env])
            phi += 0.5 / dt * np.einsum("ram,ram->r", dZMq, dZ)
            grad += dZMq / dt
        if self.ground is not None:
            z = self.z_col + host_matmul(Z[:, 2, :], self.a_col_T)                                    # (R, K) m
            pen = np.maximum(self.ground - z, 0.0)
            kc = self.kc[env]
            phi += 0.5 * np.einsum("rk,rk,rk->r", kc, pen, pen)
            fz = kc * pen                                                                          # (R, K) N up
            if self.cc is not None:  # the ground's damper on the step's mean normal velocity, where in contact
                dz = (z - self.z_start[env]) * (pen > 0)
                cd = self.cc[env] / dt
                phi += 0.5 * np.einsum("rk,rk,rk->r", cd, dz, dz)
                fz = fz - cd * dz
            grad[:, 2, :] -= host_matmul(fz, self.a_col)
            if self.mu_fric is not None:
                ut, f0, f1_over_y = self._friction(Z, env)
                coef = self.mu_fric[env][:, None] * self.N_lag[env]                          # (R, K) N
                phi += np.einsum("rk,rk->r", coef, f0)
                grad[:, :2, :] += host_matmul((coef * f1_over_y)[:, None, :] * ut, self.a_col)
        return phi, grad

    def add_hessian(self, hess: np.ndarray, Z: np.ndarray, env: np.ndarray) -> None:
        """Add the Hessian of the same terms at Z to ``hess`` (R, 3nA, 3nA) in place (contact: the active set
        at Z; friction: lagged normal force, IPC's f1/y weight)."""
        R, _, nA = Z.shape
        blocks = hess.reshape(R, 3, nA, 3, nA)
        blk = self.Hconst[env]
        if self.Mq is not None:
            blk = blk + self.Mq[env] / self.dt
        for a in range(3):
            blocks[:, a, :, a, :] += blk
        if self.ground is None:
            return
        act = self.z_col + host_matmul(Z[:, 2, :], self.a_col_T) < self.ground          # (R, K)
        w_fric = None
        if self.mu_fric is not None:
            _, _, f1_over_y = self._friction(Z, env)
            w_fric = self.mu_fric[env][:, None] * self.N_lag[env] * f1_over_y              # (R, K)
        kz = self.kc[env] + (0.0 if self.cc is None else self.cc[env] / self.dt)                 # (R, K) N/m
        for r in range(R):
            touching = np.flatnonzero(act[r])
            if len(touching):
                a_t = self.a_col[touching]
                blocks[r, 2, :, 2, :] += host_matmul(a_t.T * kz[r, touching], a_t)
            if w_fric is not None:
                loaded = np.flatnonzero(w_fric[r])
                if len(loaded):
                    a_s = self.a_col[loaded]
                    Bf = host_matmul(a_s.T * w_fric[r, loaded], a_s)
                    blocks[r, 0, :, 0, :] += Bf
                    blocks[r, 1, :, 1, :] += Bf


class ElasticTerms:
    """The elastic (cubature) part of the incremental potential, evaluated on the simulation's Warp device.

    Everything that scales with the cubature points stays on the device.  One evaluation of R
    candidate states uploads them (R × 3 × nA numbers) with their environment indices, runs one Warp
    kernel (:func:`.lbs_kernels.elastic_terms`: F = I + Z G_c, Ψ, stress and, at a step start, the
    projected 9×9 Hessian per cubature point), reduces to handle space with torch GEMMs
    (gradient Σ_c P_c G_cᵀ; Hessian Σ_c G_cᵀ H_c G_c) and downloads Σ_c V_c Ψ_c (R,), the gradient
    (R, 3, nA) and the Hessian (E, 3nA, 3nA): one synchronisation per evaluation, all buffers
    allocated once (pinned host staging on a GPU; on the CPU the host arrays are the device's).

    mu, lam: (E, C) Pa.  yield_stress: (E, C) Pa (1e301 = none) or None without plasticity.
    ``seconds`` accumulates per-phase times (CPU: wall; GPU: CUDA events when ``profile``, else only
    the host's wait); ``counts`` the evaluations.
    """

    def __init__(self, sim, mu: np.ndarray, lam: np.ndarray, yield_stress, max_rows: int, profile: bool,
                 staged: Optional[bool] = None):
        import torch

        from . import lbs_kernels as K

        wp = sim._wp
        self.torch = torch
        dev = sim.device  # Warp's device names (cpu, cuda:N) are torch's
        self.cuda = dev != "cpu"
        self.profile = bool(profile) and self.cuda
        # separate host staging buffers and copies (a GPU; on the CPU only to test that path)
        self.staged = self.cuda if staged is None else bool(staged)
        E_env, C = mu.shape
        nA = sim.n_basis
        self.E, self.C, self.nA, self.max_rows = E_env, C, nA, max_rows
        f64 = torch.float64

        def zeros(*shape, dtype=f64):
            return torch.zeros(*shape, dtype=dtype, device=dev)

        def dev_tensor(a):
            return torch.as_tensor(np.ascontiguousarray(a, np.float64), device=dev)

        G = dev_tensor(sim.cubature_G)                                      # (C, nA, 3) 1/m
        self.Gr = G.permute(0, 2, 1).reshape(3 * C, nA).contiguous()        # [(c, b), m]
        self.GrT = self.Gr.T.contiguous()                                   # [m, (c, b)]
        self.Gt = G.transpose(1, 2).contiguous()                            # (C, 3, nA)
        self.Z_rows = zeros(max_rows, 3, nA)
        self.env_rows = zeros(max_rows, dtype=torch.int32)
        self.Z_start = zeros(E_env, 3, nA)
        self.Z_plastic = zeros(E_env, 3, nA)
        self.visc = zeros(E_env)
        self.psi = zeros(max_rows, C)
        self.P = zeros(max_rows, 3, 3 * C)
        self.H = zeros(E_env, 3, C, 27)
        self.T1 = zeros(E_env, 3, C, 9, nA)
        self.result = zeros(max_rows * (3 * nA + 1))
        self.hessian = zeros(E_env, 3 * nA, 3 * nA)
        plastic_inv = torch.eye(3, dtype=f64, device=dev).repeat(E_env, C, 1, 1).contiguous()
        mu_t, lam_t, vol_t = dev_tensor(mu), dev_tensor(lam), dev_tensor(sim.cubature_volume)
        if self.staged:
            def host(t):
                return torch.empty(t.shape, dtype=t.dtype, pin_memory=self.cuda)

            self.h_Z_rows, self.h_env_rows = host(self.Z_rows), host(self.env_rows)
            self.h_Z_start, self.h_Z_plastic, self.h_visc = host(self.Z_start), host(self.Z_plastic), host(self.visc)
            self.h_result, self.h_hessian = host(self.result), host(self.hessian)
        else:
            self.h_Z_rows, self.h_env_rows = self.Z_rows, self.env_rows
            self.h_Z_start, self.h_Z_plastic, self.h_visc = self.Z_start, self.Z_plastic, self.visc
            self.h_result, self.h_hessian = self.result, self.hessian
        self.stream = None
        if self.cuda:
            self.torch_stream = torch.cuda.current_stream(dev)
            self.stream = wp.stream_from_torch(self.torch_stream)
        self.n_Z_rows, self.n_env_rows = self.h_Z_rows.numpy(), self.h_env_rows.numpy()
        self.n_Z_start, self.n_Z_plastic, self.n_visc = self.h_Z_start.numpy(), self.h_Z_plastic.numpy(), self.h_visc.numpy()
        self.n_result, self.n_hessian = self.h_result.numpy(), self.h_hessian.numpy()

        def warp(t, dtype=wp.float64):
            return wp.from_torch(t, dtype=dtype)

        self._keep = (mu_t, lam_t, vol_t, plastic_inv)
        self.launch = wp.launch(K.elastic_terms, dim=(max_rows, C),
                                inputs=[warp(self.Z_rows), warp(self.env_rows, wp.int32), warp(self.Z_start), warp(G),
                                        warp(plastic_inv, wp.mat33d), warp(mu_t), warp(lam_t), warp(vol_t),
                                        warp(self.visc), 0, warp(self.psi), warp(self.P), warp(self.H)],
                                device=sim.device, stream=self.stream, record_cmd=True)
        self.need_index = [a.label for a in K.elastic_terms.adj.args].index("need")
        self._launch_shape = (max_rows, 0)
        self.plastic_launch = None
        if yield_stress is not None:
            ys_t = dev_tensor(yield_stress)
            self._keep = self._keep + (ys_t,)
            self.plastic_launch = wp.launch(K.return_map, dim=(E_env, C),
                                            inputs=[warp(self.Z_plastic), warp(G), warp(plastic_inv, wp.mat33d),
                                                    warp(mu_t), warp(ys_t)],
                                            device=sim.device, stream=self.stream, record_cmd=True)
        self.symmetric_reduction = not self.cuda
        self.seconds: dict[str, float] = {}
        self.counts = {"hessian": 0, "trial": 0, "trial_rows": 0}
        self._events: list = []
        self._t = 0.0

    # -- timing ---------------------------------------------------------------------------------
    def _mark(self, name: str) -> None:
        """End of a phase: CUDA event on a profiled GPU run, wall clock on the CPU (where work is synchronous)."""
        if self.cuda:
            if self.profile:
                ev = self.torch.cuda.Event(enable_timing=True)
                ev.record(self.torch_stream)
                self._events.append((name, ev))
            return
        t = time.perf_counter()
        self.seconds[name] = self.seconds.get(name, 0.0) + (t - self._t)
        self._t = t

    def _start_phases(self) -> None:
        self._t = time.perf_counter()
        if self.profile:
            ev = self.torch.cuda.Event(enable_timing=True)
            ev.record(self.torch_stream)
            self._events = [("", ev)]

    def _collect_events(self) -> None:
        if not self._events:
            return
        prev = self._events[0][1]
        for name, ev in self._events[1:]:
            self.seconds[name] = self.seconds.get(name, 0.0) + 1e-3 * prev.elapsed_time(ev)
            prev = ev
        self._events = []

    def synchronize(self) -> None:
        if self.cuda:
            t = time.perf_counter()
            self.torch_stream.synchronize()
            self.seconds["wait"] = self.seconds.get("wait", 0.0) + time.perf_counter() - t
            self._collect_events()

    # -- work -----------------------------------------------------------------------------------
    def set_viscosity(self, visc: np.ndarray) -> None:
        """η/dt (E,) Pa of the Kelvin–Voigt term for the coming steps."""
        if np.array_equal(self.n_visc, visc):
            return
        self.synchronize()   # the staging buffer may still feed an earlier copy
        self.n_visc[:] = visc
        if self.staged:
            self.visc.copy_(self.h_visc, non_blocking=True)

    def evaluate(self, Z: np.ndarray, env: np.ndarray, hessian: bool = False, Z_start: Optional[np.ndarray] = None):
        """Elastic energy (R,) J, gradient (R, 3, nA) and, with ``hessian``, Hessian (R, 3nA, 3nA) of states Z.

        Z: (R, 3, nA) rows; env: (R,) their environments.  ``hessian`` needs env = 0..E−1 in order.
        Z_start: (E, 3, nA), the step start (viscous F_n); give it at the first evaluation of each step.
        """
        torch = self.torch
        R, C, nA = len(Z), self.C, self.nA
        if R > self.max_rows or (hessian and R != self.E):
            raise ValueError(f"{R} rows do not fit the LBS elastic buffers")
        self._start_phases()
        self.n_Z_rows[:R] = Z
        self.n_env_rows[:R] = env
        if Z_start is not None:
            self.n_Z_start[:] = Z_start
        if self.staged:
            self.Z_rows[:R].copy_(self.h_Z_rows[:R], non_blocking=True)
            self.env_rows[:R].copy_(self.h_env_rows[:R], non_blocking=True)
            if Z_start is not None:
                self.Z_start.copy_(self.h_Z_start, non_blocking=True)
        self._mark("upload")
        need = 2 if hessian else 1
        if (R, need) != self._launch_shape:
            self.launch.set_dim((R, C))
            self.launch.set_param_at_index(self.need_index, need)
            self._launch_shape = (R, need)
        self.launch.launch(self.stream)
        self._mark("kernel_hessian" if hessian else "kernel_trial")
        n_grad = 3 * R * nA
        torch.mm(self.P[:R].view(3 * R, 3 * C), self.Gr, out=self.result[:n_grad].view(3 * R, nA))
        torch.sum(self.psi[:R], dim=1, out=self.result[n_grad:n_grad + R])
        self._mark("reduction_gradient")
        if hessian:
            self._reduce_hessian()
            self._mark("reduction_hessian")
        if self.staged:
            self.h_result[:n_grad + R].copy_(self.result[:n_grad + R], non_blocking=True)
            if hessian:
                self.h_hessian.copy_(self.hessian, non_blocking=True)
            self._mark("download")
        self.synchronize()
        self.counts["hessian" if hessian else "trial"] += 1
        if not hessian:
            self.counts["trial_rows"] += R
        energy = self.n_result[n_grad:n_grad + R].copy()
        grad = self.n_result[:n_grad].reshape(R, 3, nA).copy()
        if not hessian:
            return energy, grad
        return energy, grad, self.n_hessian.copy()

    def _reduce_hessian(self) -> None:
        """hessian[e] = Σ_c G_cᵀ H_c G_c (3nA × 3nA), from the kernel's H: two GEMMs.

        T1[e, a, c, (b x), n] = Σ_y H[e, a, c, (b x y)] G[c, n, y]; then per block row a,
        K[(a m), (x n)] = Σ_(c b) G[c, m, b] T1[e, a, (c b), (x n)].  With ``symmetric_reduction`` (the
        CPU) only the blocks x >= a are multiplied (a third less work) and the others are filled from
        the symmetry; on a GPU one GEMM does all (fewer launches).
        """
        torch = self.torch
        E_env, C, nA = self.E, self.C, self.nA
        torch.matmul(self.H.view(E_env, 3, C, 9, 3), self.Gt, out=self.T1)
        T1 = self.T1.view(E_env, 3, 3 * C, 3 * nA)
        K4 = self.hessian.view(E_env, 3, nA, 3 * nA)
        if not self.symmetric_reduction:
            torch.matmul(self.GrT, T1, out=K4)
            return
        for a in range(3):
            K4[:, a, :, a * nA:] = torch.matmul(self.GrT, T1[:, a, :, a * nA:])
        for a in range(3):
            for x in range(a + 1, 3):
                K4[:, x, :, a * nA:(a + 1) * nA] = K4[:, a, :, x * nA:(x + 1) * nA].transpose(1, 2)

    def return_map(self, Z: np.ndarray) -> None:
        """Plastic return mapping at the accepted states Z (E, 3, nA) (updates F_p on the device)."""
        self.n_Z_plastic[:] = Z
        if self.staged:
            self.Z_plastic.copy_(self.h_Z_plastic, non_blocking=True)
        self.plastic_launch.launch(self.stream)
