//! People walking on the ground plane: random goals, a social-force model that keeps them
//! apart, pauses, and a population that turns over (people enter at the edges and leave).
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use crossview_core::{Error, Result};

/// How many people there are and how they look and move.
#[derive(Debug, Clone, PartialEq)]
pub struct PeopleConfig {
    /// Target number of people in the scene; the population hovers around it.
    pub count: usize,
    /// Preferred walking speed: mean and standard deviation in m/s.
    pub speed: [f64; 2],
    /// Body height range in metres (uniform).
    pub height: [f64; 2],
    /// Body width (shoulders, the cylinder's diameter) range in metres (uniform).
    pub width: [f64; 2],
    /// Probability of standing still for a while on reaching a goal.
    pub pause_prob: f64,
    /// Probability of walking out of the area on reaching a goal (turnover).
    pub exit_prob: f64,
    /// Probability, on reaching a goal, of joining the nearest person within 6 m and walking
    /// beside them for 5–20 s before leaving on one's own (groups that form and split).
    pub group_prob: f64,
}

impl Default for PeopleConfig {
    fn default() -> Self {
        PeopleConfig {
            count: 12,
            speed: [1.2, 0.25],
            height: [1.5, 1.95],
            width: [0.42, 0.58],
            pause_prob: 0.25,
            exit_prob: 0.15,
            group_prob: 0.0,
        }
    }
}

impl PeopleConfig {
    /// Checks ranges and probabilities.
    pub fn validate(&self) -> Result<()> {
        if self.count > 10_000 {
            return Err(Error::invalid(
                "people.count",
                format!("at most 10000, got {}", self.count),
            ));
        }
        let ok_range = |r: [f64; 2], lo: f64, hi: f64| {
            r.iter().all(|v| v.is_finite()) && lo <= r[0] && r[0] <= r[1] && r[1] <= hi
        };
        if !(ok_range([self.speed[0], self.speed[0]], 0.0, 5.0)
            && self.speed[1].is_finite()
            && self.speed[1] >= 0.0)
        {
            return Err(Error::invalid(
                "people.speed",
                format!(
                    "mean in [0, 5] m/s and std >= 0 expected, got {:?}",
                    self.speed
                ),
            ));
        }
        if !ok_range(self.height, 0.5, 3.0) {
            return Err(Error::invalid(
                "people.height",
                format!(
                    "expected min <= max within [0.5, 3] m, got {:?}",
                    self.height
                ),
            ));
        }
        if !ok_range(self.width, 0.1, 2.0) {
            return Err(Error::invalid(
                "people.width",
                format!(
                    "expected min <= max within [0.1, 2] m, got {:?}",
                    self.width
                ),
            ));
        }
        for (name, p) in [
            ("people.pause_prob", self.pause_prob),
            ("people.exit_prob", self.exit_prob),
            ("people.group_prob", self.group_prob),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(Error::invalid(name, format!("must be in [0, 1], got {p}")));
            }
        }
        if self.exit_prob + self.pause_prob + self.group_prob > 1.0 {
            return Err(Error::invalid(
                "people.group_prob",
                "exit, pause and group probabilities must add up to at most 1",
            ));
        }
        Ok(())
    }
}

/// One simulated person: a vertical cylinder standing on the ground plane.
#[derive(Debug, Clone, PartialEq)]
pub struct Person {
    /// Ground-truth identity (unique over the whole run, in order of appearance).
    pub id: u64,
    /// Ground position `[x, y]` in metres.
    pub pos: [f64; 2],
    /// Velocity in m/s.
    pub vel: [f64; 2],
    /// Body height in metres.
    pub height: f64,
    /// Body width (cylinder diameter) in metres.
    pub width: f64,
    goal: [f64; 2],
    speed: f64,
    pause_left: f64,
    exiting: bool,
    /// Walking beside another person: their id and the seconds left.
    beside: Option<(u64, f64)>,
    /// Gait phase in radians (legs and arms swing twice per stride).
    phase: f64,
}

impl Person {
    /// A person standing still at `pos` (for tests and hand-built scenes).
    pub fn standing(id: u64, pos: [f64; 2], height: f64, width: f64) -> Self {
        Person {
            id,
            pos,
            vel: [0.0, 0.0],
            height,
            width,
            goal: pos,
            speed: 0.0,
            pause_left: f64::INFINITY,
            exiting: false,
            beside: None,
            phase: 0.0,
        }
    }

    /// Silhouette width right now: the body width widened by up to 15% while the legs and
    /// arms swing (walking people's boxes breathe; standing people's do not).
    pub(crate) fn apparent_width(&self) -> f64 {
        let moving = (self.vel[0].hypot(self.vel[1]) / 1.0).min(1.0);
        self.width * (1.0 + 0.15 * moving * self.phase.sin().abs())
    }
}

/// Metres per stride (one full gait cycle).
const STRIDE_M: f64 = 1.4;

/// Social-force constants (Helbing & Molnar style), tuned for smooth, mostly collision-free
/// walking at about 1.2 m/s.
const RELAX_S: f64 = 0.5;
/// Soft, longer-range avoidance (m/s², m): people start to steer around each other early.
const REPULSION_A: f64 = 2.0;
const REPULSION_B: f64 = 0.5;
/// Stiff, short-range body contact (m/s², m): bodies barely overlap.
const BODY_A: f64 = 25.0;
const BODY_B: f64 = 0.08;
const REPULSION_RANGE: f64 = 3.0;
const ANISOTROPY: f64 = 0.35;
const MAX_SUBSTEP_S: f64 = 0.05;

/// The crowd: all people currently in (or entering/leaving) the area.
#[derive(Debug, Clone)]
pub(crate) struct Crowd {
    cfg: PeopleConfig,
    area: [f64; 2],
    people: Vec<Person>,
    next_id: u64,
    speed_dist: Normal<f64>,
}

impl Crowd {
    /// A crowd of `cfg.count` people placed at random inside `area`.
    pub fn new(cfg: &PeopleConfig, area: [f64; 2], rng: &mut ChaCha8Rng) -> Result<Self> {
        cfg.validate()?;
        let speed_dist = Normal::new(cfg.speed[0], cfg.speed[1])
            .map_err(|e| Error::invalid("people.speed", e.to_string()))?;
        let mut crowd = Crowd {
            cfg: cfg.clone(),
            area,
            people: Vec::with_capacity(cfg.count * 2),
            next_id: 0,
            speed_dist,
        };
        for _ in 0..cfg.count {
            let pos = crowd.free_spot(rng);
            crowd.spawn(pos, rng);
        }
        Ok(crowd)
    }

    /// The people currently simulated (some may be just outside the area, entering or leaving).
    pub fn people(&self) -> &[Person] {
        &self.people
    }

    /// Advances the crowd by `dt` seconds (sub-stepped for stability).
    pub fn step(&mut self, dt: f64, rng: &mut ChaCha8Rng) {
        let n = (dt / MAX_SUBSTEP_S).ceil().max(1.0) as usize;
        let h = dt / n as f64;
        for _ in 0..n {
            self.substep(h, rng);
        }
        self.turnover(dt, rng);
    }

    fn random_inside(&self, rng: &mut ChaCha8Rng) -> [f64; 2] {
        let m = 0.3_f64.min(self.area[0] / 4.0).min(self.area[1] / 4.0);
        [
            rng.random_range(m..self.area[0] - m),
            rng.random_range(m..self.area[1] - m),
        ]
    }

    /// A random point about 1 m outside one of the area's edges.
    fn random_outside(&self, rng: &mut ChaCha8Rng) -> [f64; 2] {
        let [w, d] = self.area;
        let t: f64 = rng.random();
        match rng.random_range(0..4) {
            0 => [t * w, -1.0],
            1 => [t * w, d + 1.0],
            2 => [-1.0, t * d],
            _ => [w + 1.0, t * d],
        }
    }

    /// True when nobody stands within `clearance` metres of `p`.
    fn is_free(&self, p: [f64; 2], clearance: f64) -> bool {
        self.people
            .iter()
            .all(|o| (o.pos[0] - p[0]).hypot(o.pos[1] - p[1]) > clearance)
    }

    /// A random spot inside the area not overlapping anyone (a few tries, then anywhere).
    fn free_spot(&self, rng: &mut ChaCha8Rng) -> [f64; 2] {
        let mut p = self.random_inside(rng);
        for _ in 0..20 {
            if self.is_free(p, 0.8) {
                break;
            }
            p = self.random_inside(rng);
        }
        p
    }

    fn spawn(&mut self, pos: [f64; 2], rng: &mut ChaCha8Rng) {
        let speed = self.speed_dist.sample(rng).clamp(0.4, 2.2);
        let [h0, h1] = self.cfg.height;
        let [w0, w1] = self.cfg.width;
        let person = Person {
            id: self.next_id,
            pos,
            vel: [0.0, 0.0],
            height: if h1 > h0 {
                rng.random_range(h0..h1)
            } else {
                h0
            },
            width: if w1 > w0 {
                rng.random_range(w0..w1)
            } else {
                w0
            },
            goal: self.random_inside(rng),
            speed,
            pause_left: 0.0,
            exiting: false,
            beside: None,
            phase: rng.random_range(0.0..std::f64::consts::TAU),
        };
        self.next_id += 1;
        self.people.push(person);
    }

    fn substep(&mut self, h: f64, rng: &mut ChaCha8Rng) {
        self.follow(h, rng);
        let n = self.people.len();
        let mut forces = vec![[0.0f64; 2]; n];
        for (i, f) in forces.iter_mut().enumerate() {
            let p = &self.people[i];
            let desired = if p.pause_left > 0.0 {
                [0.0, 0.0]
            } else {
                let d = [p.goal[0] - p.pos[0], p.goal[1] - p.pos[1]];
                let dist = d[0].hypot(d[1]).max(1e-9);
                // slow down on arrival
                let s = p.speed.min(dist / 0.6);
                [d[0] / dist * s, d[1] / dist * s]
            };
            f[0] = (desired[0] - p.vel[0]) / RELAX_S;
            f[1] = (desired[1] - p.vel[1]) / RELAX_S;
            let vnorm = p.vel[0].hypot(p.vel[1]);
            for (j, o) in self.people.iter().enumerate() {
                if j == i {
                    continue;
                }
                let d = [p.pos[0] - o.pos[0], p.pos[1] - o.pos[1]];
                let dist = d[0].hypot(d[1]);
                if !(1e-9..=REPULSION_RANGE).contains(&dist) {
                    continue;
                }
                let nrm = [d[0] / dist, d[1] / dist];
                // people react more to those in front of them
                let cos_phi = if vnorm > 1e-9 {
                    -(nrm[0] * p.vel[0] + nrm[1] * p.vel[1]) / vnorm
                } else {
                    0.0
                };
                let w = ANISOTROPY + (1.0 - ANISOTROPY) * (1.0 + cos_phi) / 2.0;
                let radii = (p.width + o.width) / 2.0;
                let mag = REPULSION_A * ((radii - dist) / REPULSION_B).exp() * w
                    + BODY_A * ((radii - dist) / BODY_B).exp();
                f[0] += mag * nrm[0];
                f[1] += mag * nrm[1];
            }
        }
        for (p, f) in self.people.iter_mut().zip(forces) {
            // a little sway so paths are not ruler-straight
            let sway = 0.3;
            p.vel[0] += (f[0] + sway * (rng.random::<f64>() - 0.5)) * h;
            p.vel[1] += (f[1] + sway * (rng.random::<f64>() - 0.5)) * h;
            let v = p.vel[0].hypot(p.vel[1]);
            let vmax = (p.speed * 1.3).max(0.3);
            if v > vmax {
                p.vel[0] *= vmax / v;
                p.vel[1] *= vmax / v;
            }
            p.pos[0] += p.vel[0] * h;
            p.pos[1] += p.vel[1] * h;
            p.phase = (p.phase + p.vel[0].hypot(p.vel[1]) * h / STRIDE_M * std::f64::consts::TAU)
                % std::f64::consts::TAU;
            if p.pause_left > 0.0 {
                p.pause_left -= h;
            }
        }
    }

    /// People walking beside someone aim at a spot 0.6 m to their side; when their time is
    /// up or the other has left, they walk off to a goal of their own.
    fn follow(&mut self, h: f64, rng: &mut ChaCha8Rng) {
        for i in 0..self.people.len() {
            let Some((other, left)) = self.people[i].beside else {
                continue;
            };
            let lead = self.people.iter().find(|o| o.id == other && !o.exiting);
            let spot = lead.map(|o| {
                let v = o.vel[0].hypot(o.vel[1]).max(1e-9);
                let side = [-o.vel[1] / v, o.vel[0] / v];
                let p = &self.people[i];
                let s = if (p.pos[0] - o.pos[0]) * side[0] + (p.pos[1] - o.pos[1]) * side[1] >= 0.0
                {
                    0.6
                } else {
                    -0.6
                };
                [
                    o.pos[0] + s * side[0] + 0.3 * o.vel[0],
                    o.pos[1] + s * side[1] + 0.3 * o.vel[1],
                ]
            });
            match spot {
                Some(spot) if left > h => {
                    let p = &mut self.people[i];
                    p.goal = spot;
                    p.beside = Some((other, left - h));
                }
                _ => {
                    let goal = self.random_inside(rng);
                    let p = &mut self.people[i];
                    p.goal = goal;
                    p.beside = None;
                }
            }
        }
    }

    /// The nearest person within 6 m of person `i` who is neither leaving nor walking beside
    /// someone.
    fn companion(&self, i: usize) -> Option<u64> {
        let p = &self.people[i];
        self.people
            .iter()
            .enumerate()
            .filter(|&(j, o)| j != i && !o.exiting && o.beside.is_none())
            .map(|(_, o)| (o.id, (o.pos[0] - p.pos[0]).hypot(o.pos[1] - p.pos[1])))
            .filter(|&(_, d)| d < 6.0)
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(id, _)| id)
    }

    fn turnover(&mut self, dt: f64, rng: &mut ChaCha8Rng) {
        let [w, d] = self.area;
        // goals reached: pause, leave, join someone or pick a new goal
        for i in 0..self.people.len() {
            let p = &self.people[i];
            let reached = (p.goal[0] - p.pos[0]).hypot(p.goal[1] - p.pos[1]) < 0.5;
            if !reached || p.pause_left > 0.0 || p.exiting || p.beside.is_some() {
                continue;
            }
            let u: f64 = rng.random();
            if u < self.cfg.exit_prob {
                let goal = self.random_outside(rng);
                let p = &mut self.people[i];
                p.goal = goal;
                p.exiting = true;
            } else if u < self.cfg.exit_prob + self.cfg.pause_prob {
                let pause = rng.random_range(1.0..6.0);
                let goal = self.random_inside(rng);
                let p = &mut self.people[i];
                p.pause_left = pause;
                p.goal = goal;
            } else if u < self.cfg.exit_prob + self.cfg.pause_prob + self.cfg.group_prob
                && let Some(other) = self.companion(i)
            {
                self.people[i].beside = Some((other, rng.random_range(5.0..20.0)));
            } else {
                let goal = self.random_inside(rng);
                self.people[i].goal = goal;
            }
        }
        // leavers who made it out disappear
        self.people.retain(|p| {
            !(p.exiting
                && (p.pos[0] < -0.6 || p.pos[1] < -0.6 || p.pos[0] > w + 0.6 || p.pos[1] > d + 0.6))
        });
        // newcomers enter from the edges so the population hovers around the target
        let missing = self.cfg.count.saturating_sub(self.people.len());
        if missing > 0 {
            let rate = missing as f64 * dt / 2.0;
            if rng.random::<f64>() < rate.min(1.0) {
                // enter where nobody stands; try again next step if the edges are busy
                for _ in 0..5 {
                    let pos = self.random_outside(rng);
                    if self.is_free(pos, 1.0) {
                        self.spawn(pos, rng);
                        break;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn crowd_moves_smoothly_stays_near_the_area_and_turns_over() {
        for seed in [3u64, 4, 9] {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let cfg = PeopleConfig {
                count: 15,
                ..PeopleConfig::default()
            };
            let mut crowd = Crowd::new(&cfg, [12.0, 12.0], &mut rng).unwrap();
            let mut min_gap = f64::INFINITY;
            let mut max_step: f64 = 0.0;
            let dt = 0.1;
            for _ in 0..3000 {
                let before: Vec<(u64, [f64; 2])> =
                    crowd.people().iter().map(|p| (p.id, p.pos)).collect();
                crowd.step(dt, &mut rng);
                for p in crowd.people() {
                    assert!(
                        p.pos[0] > -3.0 && p.pos[0] < 15.0 && p.pos[1] > -3.0 && p.pos[1] < 15.0
                    );
                    if let Some((_, q)) = before.iter().find(|(id, _)| *id == p.id) {
                        max_step = max_step.max((p.pos[0] - q[0]).hypot(p.pos[1] - q[1]));
                    }
                }
                let ps = crowd.people();
                for i in 0..ps.len() {
                    for j in i + 1..ps.len() {
                        min_gap = min_gap
                            .min((ps[i].pos[0] - ps[j].pos[0]).hypot(ps[i].pos[1] - ps[j].pos[1]));
                    }
                }
            }
            assert!(max_step < 0.35, "max step {max_step} m in 0.1 s");
            // body diameters are 0.42..0.58 m: bodies may touch, never pass through each other
            assert!(
                min_gap > 0.3,
                "seed {seed}: people walked through each other: {min_gap}"
            );
            assert!(crowd.next_id > 25, "only {} people ever", crowd.next_id);
            let n = crowd.people().len();
            assert!((8..=22).contains(&n), "population drifted to {n}");
        }
    }
}
