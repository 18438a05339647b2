"""A camera's own structure from motion (pycolmap incremental mapping, intrinsics fixed), its poses then aligned to the
reference trajectory (a similarity for the SfM frame, the extrinsic and delta: least squares over camera centres and
orientations). Lab experiment for issue 38 (docs/lab/2026-11-27-epipolar-hand-eye.md, "Third route"); pycolmap is not
a dependency: ``.venv/bin/pip install pycolmap==3.11.1`` first.

Usage: [OVERLAP=10] [TRI=4] [RATIO=0.1] [INIT=1,3] .venv/bin/python scripts/lab/own_sfm.py RIG CAMERA WORKDIR
(WORKDIR is deleted and recreated.)
"""
import sys, time, os, shutil
import numpy as np, torch
from pathlib import Path
import pycolmap
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from moisst_ns.rig.format import load_rig, load_calibration, Calibration
from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic, calibration_errors

root = Path(sys.argv[1]); name = sys.argv[2]; work = Path(sys.argv[3])
rig = load_rig(root); traj = ReferenceTrajectory.of(rig); cal = Calibration.from_rig(rig)
truth = load_calibration(root / "ground_truth.json")
frames = sorted(rig.frames_of(name), key=lambda f: f.timestamp)
intr = rig.sensors[name].intrinsics
t0 = time.time()
if work.exists(): shutil.rmtree(work)
(work / "img").mkdir(parents=True)
names = []
for f in frames:
    dst = work / "img" / Path(f.file_path).name; shutil.copy(root / f.file_path, dst); names.append(dst.name)
db = work / "db.db"
ro = pycolmap.ImageReaderOptions(); ro.camera_model = "PINHOLE"
ro.camera_params = ",".join(str(float(intr[k])) for k in ("fl_x", "fl_y", "cx", "cy"))
so = pycolmap.SiftExtractionOptions(); so.max_num_features = 4000
pycolmap.extract_features(db, work / "img", camera_mode=pycolmap.CameraMode.SINGLE, reader_options=ro, sift_options=so, device=pycolmap.Device.cpu)
mo = pycolmap.SequentialMatchingOptions(); mo.overlap = int(os.environ.get("OVERLAP", 10))
pycolmap.match_sequential(db, matching_options=mo, device=pycolmap.Device.cpu)
opts = pycolmap.IncrementalPipelineOptions(); opts.ba_refine_focal_length = False; opts.ba_refine_principal_point = False; opts.ba_refine_extra_params = False
opts.num_threads = 2
m = opts.mapper; m.abs_pose_refine_focal_length = False; m.abs_pose_refine_extra_params = False
m.init_min_tri_angle = float(os.environ.get("TRI", 4)); m.abs_pose_min_inlier_ratio = float(os.environ.get("RATIO", 0.1))
if os.environ.get("INIT"):
    a, b = os.environ["INIT"].split(","); opts.init_image_id1 = int(a); opts.init_image_id2 = int(b)
recs = pycolmap.incremental_mapping(db, work / "img", work / "sparse", options=opts)
print(f"sfm {time.time()-t0:.1f}s models", {k: r.num_reg_images() for k, r in recs.items()})
rec = max(recs.values(), key=lambda r: r.num_reg_images())
print(rec.summary())
idx = {n: i for i, n in enumerate(names)}
stamps = np.array([f.timestamp for f in frames]) - float(rig.trajectory_stamps[0])
K, Rs, cs = [], [], []
for im in rec.images.values():
    T = im.cam_from_world  # Rigid3d
    M = T.matrix(); R = M[:, :3]; t = M[:, 3]
    K.append(idx[im.name]); Rs.append(R.T); cs.append(-R.T @ t)  # sfm_R_cam, centre
order = np.argsort(K); K = np.array(K)[order]; Rs = np.array(Rs)[order]; cs = np.array(cs)[order]
prior = np.asarray(cal.T_ref_sensor[name]); prior_off = float(cal.time_offset[name])
def traj_at(t):
    R, p, _, _ = traj.pose_and_rates(t); return R, p
def umeyama(src, dst):
    ms, md = src.mean(0), dst.mean(0); a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a); D = np.eye(3); D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt; s = np.trace(np.diag(S) @ D) / np.sum(a**2); return s, R, md - s * R @ ms
def unpack(x):
    ext = calibrated_extrinsic(torch.from_numpy(prior), torch.from_numpy(x[:3]), torch.from_numpy(x[3:6])).numpy()
    return ext, prior_off + x[6], Rotation.from_rotvec(x[7:10]).as_matrix(), x[10:13], np.exp(x[13])
rot_w = float(os.environ.get("ROTW", 1.0))  # metres per radian
def res(x):
    ext, off, Rws, tws, s = unpack(x)
    Rr, pr = traj_at(stamps[K] + off)
    Rc = Rr @ ext[:3, :3]; pc = pr + Rr @ ext[:3, 3]
    rpos = (s * cs @ Rws.T + tws) - pc
    rrot = Rotation.from_matrix(np.einsum("nji,njk->nik", Rc, Rws @ Rs)).as_rotvec()
    return np.concatenate([rpos.ravel(), rot_w * rrot.ravel()])
# init: sim3 from centres at the prior
ext0 = prior
Rr, pr = traj_at(stamps[K] + prior_off); pc0 = pr + Rr @ ext0[:3, 3]
s, Rws, tws = umeyama(cs, pc0)
x0 = np.r_[np.zeros(7), Rotation.from_matrix(Rws).as_rotvec(), tws, np.log(s)]
def err(x):
    ext, off, *_ = unpack(x)
    tr, rot = calibration_errors(torch.from_numpy(ext), torch.from_numpy(np.asarray(truth.T_ref_sensor[name])))
    return f"{tr*100:.2f} cm / {rot:.3f} deg / {(off - truth.time_offset[name])*1000:.2f} ms", (ext[:3, 3] - np.asarray(truth.T_ref_sensor[name])[:3, 3]) * 100
print("prior", err(x0))
fit = least_squares(res, x0, method="trf", loss="soft_l1", f_scale=0.05, max_nfev=500)
print("fit", *err(fit.x), f"{time.time()-t0:.1f}s", "n", len(K))
r = fit.fun; n = len(K); print("pos rms cm", np.sqrt(np.mean(r[:3*n]**2))*100, "rot rms deg", np.rad2deg(np.sqrt(np.mean((r[3*n:]/rot_w)**2))))
J = fit.jac; cov = np.linalg.pinv(J.T @ J) * np.mean(r**2) * len(r) / (len(r) - len(fit.x))
sig = np.sqrt(np.diag(cov))
print("sigma rot deg", np.rad2deg(sig[:3]), "trans cm", sig[3:6]*100, "dt ms", sig[6]*1000)
