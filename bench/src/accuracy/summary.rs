//! What the sweep measured, reduced to orders and costs, and the run's verdict.

use trove_tests::reference::{log_log_slope, Reference};

use super::sweep::{Point, Representation};
use super::{interpolations, MIN_ORDER, ORDER_STEPS};

/// The sweep's steps from one voxel down, over which every interpolation's order is fitted.
const SWEEP_ORDER_STEPS: [f64; 4] = [1.0, 0.5, 0.25, 0.125];

/// Orders and costs drawn from the sweep.
pub(super) struct Summary {
    /// (scene, interpolation name, order of the sampling RMSE over [`SWEEP_ORDER_STEPS`]),
    /// with opacity correction.
    orders: Vec<(Reference, &'static str, Option<f64>)>,
    /// Per scene: order of trilinear's sampling RMSE over [`ORDER_STEPS`] (the check).
    asymptotic: Vec<(Reference, Option<f64>)>,
    /// Per smooth scene: time factor that halves trilinear's sampling error, over [`ORDER_STEPS`].
    pub halving_cost: Vec<(Reference, Option<f64>)>,
    /// Per scene: representation order of trilinear (RMSE against voxel size).
    representation_orders: Vec<(Reference, Option<f64>)>,
}

/// The points of `scene` with interpolation `interp` and correction, at `steps`.
fn series<'a>(points: &'a [Point], scene: Reference, interp: &str, steps: &[f64]) -> Vec<&'a Point> {
    points
        .iter()
        .filter(|p| p.scene == scene && p.interpolation.name() == interp && p.correction && steps.contains(&p.step))
        .collect()
}

/// The order of the sampling error over a series' steps.
fn sampling_order(series: &[&Point]) -> Option<f64> {
    log_log_slope(&series.iter().map(|p| (p.step, p.sampling_rmse)).collect::<Vec<_>>())
}

impl Summary {
    pub fn new(points: &[Point], representation: &[Representation]) -> Summary {
        let mut orders = Vec::new();
        let mut asymptotic = Vec::new();
        let mut halving_cost = Vec::new();
        for scene in Reference::ALL {
            for i in interpolations() {
                orders.push((scene, i.name(), sampling_order(&series(points, scene, i.name(), &SWEEP_ORDER_STEPS))));
            }
            let s = series(points, scene, "trilinear", &ORDER_STEPS);
            asymptotic.push((scene, sampling_order(&s)));
            if scene.smooth() {
                // time ∝ error^k, so halving the error multiplies the time by 2^(−k).
                let k = log_log_slope(&s.iter().map(|p| (p.sampling_rmse, p.seconds)).collect::<Vec<_>>());
                halving_cost.push((scene, k.map(|k| 2f64.powf(-k))));
            }
        }
        let representation_orders = Reference::ALL
            .iter()
            .map(|&scene| {
                let pts: Vec<(f64, f64)> =
                    representation.iter().filter(|r| r.scene == scene).map(|r| (1.0 / r.dims as f64, r.rmse)).collect();
                (scene, log_log_slope(&pts))
            })
            .collect();
        Summary { orders, asymptotic, halving_cost, representation_orders }
    }

    /// Trilinear's asymptotic order on `scene`.
    pub fn asymptotic_order(&self, scene: Reference) -> Option<f64> {
        self.asymptotic.iter().find(|o| o.0 == scene).and_then(|o| o.1)
    }

    /// The order of `interp` on `scene` over the sweep's steps 1 … ⅛ voxel.
    pub fn order(&self, scene: Reference, interp: &str) -> Option<f64> {
        self.orders.iter().find(|o| o.0 == scene && o.1 == interp).and_then(|o| o.2)
    }

    /// Trilinear's representation order on `scene`.
    pub fn representation_order(&self, scene: Reference) -> Option<f64> {
        self.representation_orders.iter().find(|o| o.0 == scene).and_then(|o| o.1)
    }

    /// The smallest asymptotic trilinear order over the smooth scenes (0 where none could
    /// be fitted, which fails the check).
    pub fn worst_trilinear_order(&self) -> f64 {
        Reference::ALL
            .iter()
            .filter(|s| s.smooth())
            .map(|&s| self.asymptotic_order(s).unwrap_or(0.0))
            .fold(f64::INFINITY, f64::min)
    }

    /// The verdict: trilinear with correction converges at least at [`MIN_ORDER`] on every
    /// smooth scene.
    pub fn passes(&self) -> bool {
        self.worst_trilinear_order() >= MIN_ORDER
    }

    /// The verdict with the orders behind it, one line.
    pub fn check_line(&self) -> String {
        let orders: Vec<String> = Reference::ALL
            .iter()
            .filter(|s| s.smooth())
            .map(|&s| format!("{} {:.2}", s.name(), self.asymptotic_order(s).unwrap_or(f64::NAN)))
            .collect();
        format!(
            "{}: trilinear + opacity correction, sampling-error order over steps ¼ … 1/32 voxel: {} \
             (required ≥ {MIN_ORDER})",
            if self.passes() { "PASS" } else { "FAIL" },
            orders.join(", ")
        )
    }
}

#[cfg(test)]
mod tests {
    use super::super::sweep::tests::point;
    use super::*;

    /// Trilinear points on every smooth scene whose sampling error falls as step^order.
    fn converging(order: f64) -> Vec<Point> {
        let mut points = Vec::new();
        for scene in Reference::ALL.into_iter().filter(|s| s.smooth()) {
            for step in ORDER_STEPS {
                let e = 1e-3 * step.powf(order);
                points.push(Point { scene, ..point(step, 1.0 / step, e, e) });
            }
        }
        points
    }

    #[test]
    fn second_order_passes_and_first_order_fails() {
        let pass = Summary::new(&converging(2.0), &[]);
        assert!((pass.worst_trilinear_order() - 2.0).abs() < 1e-9);
        assert!(pass.passes() && pass.check_line().starts_with("PASS"), "{}", pass.check_line());
        let fail = Summary::new(&converging(1.0), &[]);
        assert!(!fail.passes() && fail.check_line().starts_with("FAIL"), "{}", fail.check_line());
        // A scene whose order cannot be fitted fails too.
        let mut missing = converging(2.0);
        missing.retain(|p| p.scene != Reference::Ramp);
        assert!(!Summary::new(&missing, &[]).passes());
    }
}
