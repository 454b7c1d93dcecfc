"""Speed and accuracy of the hand model, shape fit (Eq. 8) and global translation (Eq. 5).

    python benchmarks/bench_hand_model.py [--hands 1000] [--tracks 30] [--seed 0]
"""
import argparse
import time

import numpy as np

from handmocap.perception.hand_model import HandModel
from handmocap.perception.joint_limits import JointLimits
from handmocap.perception.shape import ShapeFitter, ShapeTracker, bone_ratios
from handmocap.perception.translation import camera_joints_from_keypoints, root_fitting_keypoints


def timed(fn, repeat):
    fn()
    t = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t) / repeat


def shape_error_bound(fitter, model, limits, frames, rng, samples=2000):
    """Lowest beta RMS error any estimator can reach from `frames` frames of 5%-noisy joints:
    the Bayesian Cramer-Rao bound sqrt(tr((n J' S^-1 J + I)^-1) / B), with J (bones, B) the
    Jacobian of bone ratios in beta at 0, S the per-frame covariance of the ratio noise
    (measured on sampled poses) and the N(0, I) prior on beta."""
    bones = list(fitter.bones)
    _, jac = fitter.ratios_and_jacobian(np.zeros(fitter.num_betas))
    jac = jac[:, fitter.free]                    # the fitted coefficients (hand_size is given, not fitted)
    _, joints = model.forward(limits.sample(samples, rng))
    xyz = (joints - joints[:, 9:10]) / model.ref_bone_length()
    noise = bone_ratios(xyz + rng.normal(0, 0.05, xyz.shape)) - bone_ratios(xyz)
    S = np.cov(noise[:, bones].T)
    fisher = frames * jac[bones].T @ np.linalg.solve(S, jac[bones])
    return float(np.sqrt(np.trace(np.linalg.inv(fisher + np.eye(len(fitter.free)))) / len(fitter.free)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hands", type=int, default=1000)
    ap.add_argument("--tracks", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    model = HandModel.load()
    limits = JointLimits.for_model(model)
    names = model.beta_names

    pose, beta = limits.sample(1, rng)[0], rng.normal(size=10)
    poses, betas = limits.sample(256, rng), rng.normal(size=(256, 10))
    print(f"model: {len(model.v_template)} vertices, {len(model.faces)} triangles, {model.num_betas} betas")
    print(f"forward, one hand:        {timed(lambda: model.forward(pose, beta), 200) * 1e3:.2f} ms")
    print(f"forward, batch of 256:    {timed(lambda: model.forward(poses, betas), 5) * 1e3:.1f} ms")

    # per-frame fit on clean synthetic hands: random beta ~ N(0,1), random plausible poses; hand_size
    # 0: the size comes from hand_length (HandModel.sized), ratios do not fit it (handmocap/perception/shape.py)
    size = names.index("hand_size")
    betas = rng.normal(size=(args.hands, 10))
    betas[:, size] = 0.0
    _, joints = model.forward(limits.sample(args.hands, rng), betas)
    xyz = (joints - joints[:, 9:10]) / model.ref_bone_length(betas)[:, None, None]
    for tips in (True, False):
        fitter = ShapeFitter(model, include_tips=tips)
        fitted = np.array([fitter.fit(x) for x in xyz])
        ratio_err = np.array([np.abs(fitter.model_ratios(b) / bone_ratios(x) - 1)[fitter.bones].mean()
                              for b, x in zip(fitted, xyz)])
        all_err = np.array([np.abs(fitter.model_ratios(b) / bone_ratios(x) - 1)[1:].mean()
                            for b, x in zip(fitted, xyz)])
        rms = np.sqrt(np.mean((fitted - betas) ** 2, axis=0))
        print(f"shape fit ({'19 bones, tips included' if tips else '14 bones, tips excluded'}): "
              f"{timed(lambda: fitter.fit(xyz[0]), 500) * 1e3:.3f} ms/fit; bone-ratio error mean "
              f"{ratio_err.mean() * 100:.3f}% (fitted bones), {all_err.mean() * 100:.3f}% (all 19), "
              f"max {ratio_err.max() * 100:.3f}%; beta RMS error {np.sqrt(np.mean(rms[fitter.free] ** 2)):.3f} (9 fitted)")
        print("   per coefficient: " + ", ".join(f"{n} {r:.3f}" for n, r in zip(names, rms)))

    # running estimate over a track: 5% noise (sigma = 0.05 reference bone per coordinate)
    fitter = ShapeFitter(model)
    unobservable = [names.index(n) for n in ("hand_size", "finger_thickness", "wrist_girth")]
    observable = [k for k in range(10) if k not in unobservable]
    for frames in (100, 1000):
        tracks = args.tracks if frames == 100 else max(args.tracks // 6, 3)
        errors, ratio_err, times = [], [], []
        for _ in range(tracks):
            beta = rng.normal(size=10)
            beta[size] = 0.0
            _, joints = model.forward(limits.sample(frames, rng), beta)
            xyz = (joints - joints[:, 9:10]) / model.ref_bone_length(beta) + rng.normal(0, 0.05, joints.shape)
            tracker = ShapeTracker(fitter, window=frames)
            t = time.perf_counter()
            for x in xyz:
                est, n = tracker.update(x)
            times.append((time.perf_counter() - t) / frames)
            errors.append(est - beta)
            ratio_err.append(np.abs(fitter.model_ratios(est) / fitter.model_ratios(beta) - 1)[1:].mean())
        e = np.array(errors)
        print(f"tracker, 5% joint noise, {frames} frames, {tracks} tracks: beta RMS {np.sqrt(np.mean(e[:, fitter.free] ** 2)):.3f} (9 fitted), "
              f"{np.sqrt(np.mean(e[:, observable] ** 2)):.3f} (7 ratio-observable); bone ratios within "
              f"{np.mean(ratio_err) * 100:.2f}% mean; {np.mean(times) * 1e3:.2f} ms/update")
        print("   per coefficient: " + ", ".join(f"{n} {r:.2f}" for n, r in zip(names, np.sqrt(np.mean(e ** 2, 0)))))
        print(f"   no estimator can do better than: beta RMS {shape_error_bound(fitter, model, limits, frames, rng):.3f}"
              " (Bayesian Cramer-Rao bound, same noise and prior)")

    # global translation on synthetic projections
    K = np.array([[615.0, 0, 320.0], [0, 615.0, 240.0], [0, 0, 1]])
    n = args.hands
    poses = limits.sample(n, rng, wrist=rng.normal(0, 1.0, (n, 3)))
    _, joints = model.forward(poses)
    depth = rng.uniform(0.3, 1.5, n)
    xyz = joints - joints[:, 9:10] + np.stack([rng.uniform(-0.15, 0.15, n), rng.uniform(-0.1, 0.1, n), depth], -1)[:, None]
    uv = xyz @ K.T
    uv = uv[..., :2] / uv[..., 2:]
    ref = np.linalg.norm(xyz[:, 0] - xyz[:, 9], axis=-1)
    rel = (xyz - xyz[:, 9:10]) / ref[:, None, None]
    for noise in (0.0, 2.0):
        noisy = uv + rng.normal(0, noise, uv.shape)
        t = time.perf_counter()
        _, root, valid = camera_joints_from_keypoints(K, noisy, rel, ref)
        dt = (time.perf_counter() - t) / n
        err = np.linalg.norm(root - xyz[:, 9], axis=-1) / depth
        print(f"translation, {noise:.0f} px noise: valid {valid.mean() * 100:.1f}%; root error / depth: "
              f"max {err[valid].max():.2e} (valid), median {np.median(err):.2e}, 90th pct {np.percentile(err, 90):.2e} "
              f"(all, fallback included); {dt * 1e6:.1f} us/hand batched")
        t = time.perf_counter()
        root, ok = root_fitting_keypoints(K, noisy, rel * ref[:, None, None])
        dt = (time.perf_counter() - t) / n
        err = np.linalg.norm(root - xyz[:, 9], axis=-1) / depth
        print(f"   all-joint least-squares fit (what pose.py uses): ok {ok.mean() * 100:.1f}%; root error / depth: "
              f"max {np.nanmax(err):.2e}, median {np.nanmedian(err):.2e}, 90th pct {np.nanpercentile(err, 90):.2e}; "
              f"{dt * 1e6:.1f} us/hand batched")


if __name__ == "__main__":
    main()
