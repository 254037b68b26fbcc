#pragma once
/// @file
/// Every numerical tolerance of cscam and of its tests, in one place.
namespace cscam::tol {

/// Kinematic round trips (IK then FK) must close to this.
inline constexpr double kRoundTripMm = 1e-9;
inline constexpr double kRoundTripRad = 1e-10;
/// Default chord tolerance of the post's linearisation (tip deviation from the CL segment).
inline constexpr double kLinearisationMm = 0.01;
/// Default angular tolerance of the tool axis during linearisation.
inline constexpr double kAxisDeviationRad = 0.005;  // ~0.29 deg
/// Below this, a tool axis counts as parallel to the primary rotary axis (IK singularity).
inline constexpr double kSingularRad = 1e-9;
/// A tool axis at most this far outside the orientations a machine can reach (the small cone about the primary rotary
/// that a calibrated serial machine's tilted axes leave unreachable, the edge of a nutating head's band, a calibrated
/// XMINI wrist's twist psi or gauge offset near its pole) is reached as
/// nearly as the machine can: its IK returns the nearest reachable axis and says how far off it is
/// (kin::Solution::axis_error_rad). Half the default axis tolerance: calibration tilts axes by tens to hundreds of
/// microradians, so such cones are well inside it; the gate still judges every deviation against the post's tolerance.
inline constexpr double kReachSlackRad = 0.5 * kAxisDeviationRad;
/// Allowed slack when comparing an axis value to its limit (floating-point noise only).
inline constexpr double kLimitSlackMm = 1e-7;
inline constexpr double kLimitSlackDeg = 1e-7;
/// An IK solution at most this far past a rotary limit is taken at the limit (the linear axes solved again for the same
/// tip): a CL tool vector printed with 5 or 6 decimals is off by up to about 6e-4 deg, and a path along a limit would
/// otherwise flip its rotaries wherever rounding put a point beyond it. The tool axis then turns by at most this much,
/// far inside the axis tolerance that the gate judges.
inline constexpr double kLimitSnapDeg = 1e-3;
/// Hysteresis for counting a reversal in statistics.
inline constexpr double kReversalHysteresisMm = 0.002;
inline constexpr double kReversalHysteresisDeg = 0.01;
/// What verification and the safety gate allow on top of the post's own tolerances: the rounding of
/// printed axis words (4-5 decimals) and of the FK samples. One place for verify, plan and the gate.
inline constexpr double kVerifySlackMm = 0.002;
inline constexpr double kVerifySlackDeg = 0.01;

}  // namespace cscam::tol

// Calibration (calib module and its tests).
namespace cscam::tol {
/// Noise-free recovery of injected parameter errors (file units: mm, deg).
inline constexpr double kCalibRecoveryNoiseFree = 1e-8;
/// Automatic vs central finite-difference Jacobian (relative to the column norm).
inline constexpr double kCalibJacobianRel = 1e-6;
/// A scaled singular value below this times the largest counts as zero (unidentifiable).
inline constexpr double kCalibRankRel = 1e-7;
}  // namespace cscam::tol

// Diagnosis (tests/diagnose_test.cpp): a recovered effect parameter must lie within this fraction of the truth.
namespace cscam::tol {
inline constexpr double kDiagnoseParamRel = 0.2;
/// A vibration's frequency from a recording with rows missing (the spectrum's bin is 1/duration: 0.04 Hz for 25 s).
inline constexpr double kDiagnoseFrequencyHz = 0.1;
/// A first-order servo's time constant, relative to the truth (a parameter that enters nonlinearly).
inline constexpr double kDiagnoseTauRel = 0.1;
/// A permanent step's time, in seconds (the fit keeps the time of the largest jump at the analysis samples).
inline constexpr double kDiagnoseStepTimeS = 0.05;
}  // namespace cscam::tol
