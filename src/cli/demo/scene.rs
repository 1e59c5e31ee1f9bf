//! A synthetic street for `readi demo --model bevfusion`: flat ground and a few cars as
//! boxes, seen by a 32-beam spinning lidar (ray-cast returns: x, y, z, intensity, time
//! lag, nuScenes' five columns) and by six cameras around the ego car (nuScenes' order:
//! front, front right, back right, back, back left, front left), each view rendered by
//! casting a ray per pixel. The calibration is what mmdet3d's pipeline hands BEVFusion:
//! intrinsics, camera-to-lidar transforms, and identity image and lidar augmentations (the
//! views are rendered at the model's size).
//!
//! Everything is in the lidar frame: x forward, y left, z up, the sensor at the origin,
//! the ground 1.8 m below it.

use std::f64::consts::PI;

/// The ground plane's height in the lidar frame.
const GROUND_Z: f64 = -1.8;
/// How far the lidar sees.
const MAX_RANGE: f64 = 60.0;

/// A car: an upright box with its centre on the ground, a yaw, and a grey level.
#[derive(Clone, Copy, Debug)]
pub struct Car {
    pub x: f64,
    pub y: f64,
    pub yaw: f64,
    pub shade: f32,
}

/// Length, width and height of every car.
const CAR: [f64; 3] = [4.5, 1.9, 1.6];

/// The cars of frame `frame`: parked ones and two that drive along.
pub fn cars(frame: usize) -> Vec<Car> {
    let t = frame as f64;
    vec![
        Car { x: 8.0 + 1.5 * t, y: -3.5, yaw: 0.0, shade: 0.75 },
        Car { x: -12.0, y: 3.2, yaw: 0.05, shade: 0.3 },
        Car { x: 18.0, y: 4.0, yaw: PI / 2.0, shade: 0.55 },
        Car { x: -6.0 - t, y: -9.0, yaw: 0.4, shade: 0.85 },
    ]
}

/// The first hit of the ray `o + s d` (s > 0): its distance and what it hit (`None`:
/// the ground).
fn hit(o: [f64; 3], d: [f64; 3], cars: &[Car]) -> Option<(f64, Option<usize>)> {
    let mut best = if d[2] < -1e-9 { Some(((GROUND_Z - o[2]) / d[2], None)) } else { None };
    for (i, c) in cars.iter().enumerate() {
        // The ray in the car's frame, then the slab test against the box.
        let (s, co) = c.yaw.sin_cos();
        let rel = [o[0] - c.x, o[1] - c.y, o[2] - (GROUND_Z + CAR[2] / 2.0)];
        let lo = [co * rel[0] + s * rel[1], -s * rel[0] + co * rel[1], rel[2]];
        let ld = [co * d[0] + s * d[1], -s * d[0] + co * d[1], d[2]];
        let (mut near, mut far) = (0.0f64, f64::INFINITY);
        for a in 0..3 {
            let half = CAR[a] / 2.0;
            if ld[a].abs() < 1e-12 {
                if lo[a].abs() > half {
                    far = -1.0;
                }
                continue;
            }
            let (t0, t1) = ((-half - lo[a]) / ld[a], (half - lo[a]) / ld[a]);
            near = near.max(t0.min(t1));
            far = far.min(t0.max(t1));
        }
        if near <= far && near > 1e-6 && best.is_none_or(|(b, _)| near < b) {
            best = Some((near, Some(i)));
        }
    }
    best.filter(|(s, _)| *s <= MAX_RANGE)
}

/// One sweep: 32 beams from -30 to +10 degrees, 0.4 degrees apart in azimuth; rows of
/// (x, y, z, intensity, time lag 0). Ground returns are weak (intensity 0.1 to 0.2, a
/// lane-marking pattern), cars strong (0.5 to 0.9).
pub fn sweep(cars: &[Car]) -> Vec<f32> {
    let mut out = Vec::new();
    for beam in 0..32 {
        let elevation = (-30.0 + 40.0 * beam as f64 / 31.0).to_radians();
        for step in 0..900 {
            let azimuth = (step as f64 * 0.4).to_radians();
            let d = [elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin()];
            let Some((s, what)) = hit([0.0; 3], d, cars) else { continue };
            let p = [s * d[0], s * d[1], s * d[2]];
            let intensity = match what {
                Some(i) => 0.5 + 0.4 * cars[i].shade,
                None if (p[1].rem_euclid(3.5)) < 0.15 => 0.2,
                None => 0.1,
            };
            out.extend([p[0] as f32, p[1] as f32, p[2] as f32, intensity, 0.0]);
        }
    }
    out
}

/// A camera, by its yaw in the lidar frame (0 looks along x).
struct View {
    yaw: f64,
}

/// nuScenes' six cameras by yaw: front, front right, back right, back, back left, front left.
const VIEWS: [View; 6] = [
    View { yaw: 0.0 },
    View { yaw: -0.96 },
    View { yaw: -1.92 },
    View { yaw: PI },
    View { yaw: 1.92 },
    View { yaw: 0.96 },
];

/// The camera's axes (x right, y down, z forward) in the lidar frame at `yaw`, columns.
fn camera_rotation(yaw: f64) -> [[f64; 3]; 3] {
    let (s, c) = yaw.sin_cos();
    // Camera z (forward) = (c, s, 0); camera x (right) = (s, -c, 0); camera y (down) = -z.
    [[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]]
}

/// Focal length in pixels for a 70 degree horizontal field of view across `w` pixels.
fn focal(w: usize) -> f64 {
    w as f64 / 2.0 / (35.0f64).to_radians().tan()
}

/// The calibration of `cams` views of `h` x `w` pixels, each `[1, cams, 4, 4]` (row-major):
/// camera_intrinsics, camera2lidar, img_aug_matrix; and lidar_aug_matrix `[1, 4, 4]`.
pub fn calibration(cams: usize, h: usize, w: usize) -> [Vec<f32>; 4] {
    let eye = |m: &mut Vec<f32>| m.extend((0..16).map(|i| if i % 5 == 0 { 1.0 } else { 0.0 }));
    let (mut k, mut c2l, mut aug, mut lidar) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for view in VIEWS.iter().cycle().take(cams) {
        let f = focal(w) as f32;
        k.extend([f, 0.0, w as f32 / 2.0, 0.0, 0.0, f, h as f32 / 2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        let r = camera_rotation(view.yaw);
        for row in r {
            c2l.extend([row[0] as f32, row[1] as f32, row[2] as f32, 0.0]);
        }
        c2l.extend([0.0, 0.0, 0.0, 1.0]);
        eye(&mut aug);
    }
    eye(&mut lidar);
    [k, c2l, aug, lidar]
}

/// The six views `[1, cams, 3, h, w]` in [0, 1], before the camera's exposure and noise:
/// sky, ground with lane markings, cars by their shade; darker with distance.
pub fn views(cars: &[Car], cams: usize, h: usize, w: usize) -> Vec<f32> {
    let f = focal(w);
    let mut out = vec![0.0f32; cams * 3 * h * w];
    for (v, view) in VIEWS.iter().cycle().take(cams).enumerate() {
        let r = camera_rotation(view.yaw);
        for y in 0..h {
            for x in 0..w {
                let cam = [(x as f64 + 0.5 - w as f64 / 2.0) / f, (y as f64 + 0.5 - h as f64 / 2.0) / f, 1.0];
                let d = [0, 1, 2].map(|i| r[i][0] * cam[0] + r[i][1] * cam[1] + r[i][2] * cam[2]);
                let rgb = match hit([0.0; 3], d, cars) {
                    None => [0.35 + 0.15 * (y as f32 / h as f32), 0.45, 0.6],
                    Some((s, None)) => {
                        let lane = (s * d[1]).rem_euclid(3.5) < 0.15;
                        let g = if lane { 0.7 } else { 0.3 } * (1.0 - (s / MAX_RANGE) as f32 * 0.5);
                        [g, g, g * 0.95]
                    }
                    Some((s, Some(i))) => {
                        let g = 0.8 * cars[i].shade * (1.0 - (s / MAX_RANGE) as f32 * 0.5);
                        [g, g * 0.9, g * 0.8]
                    }
                };
                for (c, value) in rgb.into_iter().enumerate() {
                    out[((v * 3 + c) * h + y) * w + x] = value.clamp(0.0, 1.0);
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ray straight down hits the ground 1.8 m below; one along x hits the first car's
    /// rear face, 8 - 2.25 m ahead.
    #[test]
    fn rays_hit_the_ground_and_the_cars_where_they_are() {
        let cars = cars(0);
        let (s, what) = hit([0.0; 3], [0.0, 0.0, -1.0], &cars).expect("ground");
        assert!((s - 1.8).abs() < 1e-9 && what.is_none());
        let beside = [Car { x: 8.0, y: 0.0, yaw: 0.0, shade: 0.5 }];
        let (s, what) = hit([0.0, 0.0, -1.0], [1.0, 0.0, 0.0], &beside).expect("car");
        assert!((s - 5.75).abs() < 1e-9 && what == Some(0), "{s}");
    }

    /// The front camera's centre pixel looks along x; its rotation is orthonormal.
    #[test]
    fn the_front_camera_looks_forward() {
        let r = camera_rotation(0.0);
        assert_eq!([r[0][2], r[1][2], r[2][2]], [1.0, 0.0, 0.0]);
        for a in 0..3 {
            for b in 0..3 {
                let dot: f64 = (0..3).map(|i| r[i][a] * r[i][b]).sum();
                assert!((dot - if a == b { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
    }
}
