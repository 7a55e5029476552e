// A peer tracker for bench/rack_visp_peer.py: ViSP's model-based tracker (vpMbGenericTracker, moving edges,
// optionally with KLT points on the model's cylinders) over an image sequence, started from a given pose.
//
// Usage: rack_peer MODEL.cao FRAMES_DIR N_FRAMES PX PY U0 V0 INIT_POSE_FILE MODE OUT_FILE
//   FRAMES_DIR holds frame_00000.pgm ... (8-bit grey); PX PY U0 V0 the pinhole camera (pixels, no distortion);
//   INIT_POSE_FILE 16 numbers, the 4x4 cMo (rack/object frame -> camera frame, row major) of the first frame;
//   MODE "hybrid" (edges + KLT, as the evaluation ran ViSP 3.5) or "edge".
// Writes one line per frame to OUT_FILE: "ok r00 r01 r02 tx r10 r11 r12 ty r20 r21 r22 tz" (cMo) with ok 1, or
// "0" and the last pose when ViSP threw (the tracker is then started again from the last pose).
// Settings are ViSP's tutorial values (tutorial-mb-generic-tracker), not tuned on our scenes.
#include <visp3/core/vpCameraParameters.h>
#include <visp3/core/vpHomogeneousMatrix.h>
#include <visp3/core/vpImage.h>
#include <visp3/core/vpMath.h>
#include <visp3/io/vpImageIo.h>
#include <visp3/klt/vpKltOpencv.h>
#include <visp3/mbt/vpMbGenericTracker.h>
#include <visp3/me/vpMe.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <string>

static double env_or(const char *name, double fallback)
{
  const char *v = std::getenv(name);
  return v != nullptr && *v != '\0' ? std::stod(v) : fallback;
}

int main(int argc, char **argv)
{
  if (argc != 11) {
    std::cerr << "usage: rack_peer MODEL.cao FRAMES_DIR N_FRAMES PX PY U0 V0 INIT_POSE_FILE hybrid|edge OUT_FILE\n";
    return 2;
  }
  const std::string model = argv[1], dir = argv[2], mode = argv[9], out_path = argv[10];
  const int n_frames = std::stoi(argv[3]);
  const vpCameraParameters cam(std::stod(argv[4]), std::stod(argv[5]), std::stod(argv[6]), std::stod(argv[7]));
  vpHomogeneousMatrix cMo;
  {
    std::ifstream f(argv[8]);
    for (unsigned i = 0; i < 4; ++i)
      for (unsigned j = 0; j < 4; ++j)
        if (!(f >> cMo[i][j])) {
          std::cerr << "rack_peer: " << argv[8] << ": expected 16 numbers\n";
          return 2;
        }
  }
  if (mode != "hybrid" && mode != "edge") {
    std::cerr << "rack_peer: mode must be hybrid or edge, got " << mode << "\n";
    return 2;
  }
  const int type = mode == "hybrid" ? (vpMbGenericTracker::EDGE_TRACKER | vpMbGenericTracker::KLT_TRACKER)
                                    : vpMbGenericTracker::EDGE_TRACKER;
  vpMbGenericTracker tracker(1, type);
  // Moving-edge settings: ViSP's tutorial values unless overridden by the environment (RACK_PEER_ME_RANGE,
  // _THRESHOLD, _STEP, _MU), which bench/rack_visp_peer.py passes from its --me-* options.
  vpMe me;
  me.setMaskSize(5);
  me.setMaskNumber(180);
  me.setRange(static_cast<unsigned int>(env_or("RACK_PEER_ME_RANGE", 8)));
  me.setThreshold(env_or("RACK_PEER_ME_THRESHOLD", 10000));
  me.setMu1(env_or("RACK_PEER_ME_MU", 0.5));
  me.setMu2(env_or("RACK_PEER_ME_MU", 0.5));
  me.setSampleStep(env_or("RACK_PEER_ME_STEP", 4));
  tracker.setMovingEdge(me);
  if (mode == "hybrid") {
    vpKltOpencv klt;
    klt.setMaxFeatures(300);
    klt.setWindowSize(5);
    klt.setQuality(0.015);
    klt.setMinDistance(8);
    klt.setHarrisFreeParameter(0.01);
    klt.setBlockSize(3);
    klt.setPyramidLevels(3);
    tracker.setKltOpencv(klt);
    tracker.setKltMaskBorder(5);
  }
  tracker.setCameraParameters(cam);
  tracker.loadModel(model);
  tracker.setDisplayFeatures(false);
  tracker.setAngleAppear(vpMath::rad(70));
  tracker.setAngleDisappear(vpMath::rad(80));
  tracker.setNearClippingDistance(0.1);
  tracker.setFarClippingDistance(100.0);
  tracker.setClipping(tracker.getClipping() | vpPolygon3D::FOV_CLIPPING);

  std::ofstream out(out_path);
  out.precision(12);
  vpImage<unsigned char> I;
  char name[64];
  for (int k = 0; k < n_frames; ++k) {
    std::snprintf(name, sizeof(name), "/frame_%05d.pgm", k);
    vpImageIo::read(I, dir + name);
    int ok = 1;
    try {
      if (k == 0)
        tracker.initFromPose(I, cMo);
      tracker.track(I);
      tracker.getPose(cMo);
    } catch (const vpException &e) {
      ok = 0;  // keep the last pose; start again from it on the next frame
      try {
        tracker.initFromPose(I, cMo);
      } catch (const vpException &) {
      }
    }
    out << ok;
    for (unsigned i = 0; i < 3; ++i)
      for (unsigned j = 0; j < 4; ++j)
        out << ' ' << cMo[i][j];
    out << '\n';
  }
  return 0;
}
