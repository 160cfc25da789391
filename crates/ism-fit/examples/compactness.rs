//! The compactness table of BENCHMARKS.md (section fit): fitted ISM versus the linear isocomplex
//! (marching triangles / tetrahedra) on the same complex and on finer uniform Kuhn grids.
//!
//! `cargo run --release -p ism-fit --example compactness [-- NAME RES TOL ...]`
//! Errors are max `|g|/|∇g|` over dense samples of the shape (the same sampler for both).
use ism_fit::fit::{grid_cells, linear_baseline, linear_error};
use ism_fit::{fit, FitOptions, Preset};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let cases: Vec<(String, usize, f64)> = if args.is_empty() {
        vec![
            ("circle".into(), 6, 1e-4),
            ("taubin".into(), 8, 1e-3),
            ("sphere".into(), 8, 2e-3),
            ("torus".into(), 8, 2e-3),
        ]
    } else {
        args.chunks(3)
            .map(|c| {
                (
                    c[0].clone(),
                    c[1].parse().unwrap_or(8),
                    c[2].parse().unwrap_or(1e-3),
                )
            })
            .collect()
    };
    println!("| shape | model | grid | simplices | stage parameters | stored numbers | max abs(g)/grad | topology (components, χ) | fit time |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for (name, res, tol) in cases {
        let preset = Preset::find(&name)?;
        let g = preset.expression()?;
        let truth = (preset.components, preset.euler);
        for (pv, rational) in [(true, false), (true, true), (false, false)] {
            let mut options = FitOptions::new(preset.domain);
            options.resolution = res;
            options.tolerance = tol;
            options.topology = pv;
            options.rational = rational;
            let fitted = fit(&g, &options, &ism_format::Progress::none())?;
            let r = &fitted.report;
            let topo = (r.topology.components, r.topology.euler);
            println!(
                "| {name} | ISM{}, PV {} | Kuhn {res} + adaptive | {} | {} | {} | {:.2e} | {:?}{} | {:.1} s |",
                if rational { " + rational" } else { "" },
                if pv { "on" } else { "off" },
                r.simplices,
                r.parameters,
                r.stored_numbers,
                r.max_distance,
                topo,
                if topo == truth { " = true" } else { " ≠ true" },
                r.seconds
            );
            if pv && !rational {
                let (cells, stored, err) = linear_error(&g, &fitted.complex);
                println!("| {name} | linear, same complex | (as above) | {cells} | 0 | {stored} | {err:.2e} | | |");
            }
        }
        // Uniform grids, doubling until the linear isocomplex is as accurate as the ISM (PV on).
        let mut options = FitOptions::new(preset.domain);
        options.resolution = res;
        options.tolerance = tol;
        let target = fit(&g, &options, &ism_format::Progress::none())?
            .report
            .max_distance;
        let limit = if preset.dim == 2 { 2048 } else { 64 };
        let mut r = res;
        loop {
            let (cells, stored, err) = linear_baseline(&g, preset.domain, r);
            let grid: Vec<String> = grid_cells(preset.domain, r)
                .iter()
                .map(|c| c.to_string())
                .collect();
            println!(
                "| {name} | linear, uniform | Kuhn {} | {cells} | 0 | {stored} | {err:.2e} | | |",
                grid.join("×")
            );
            if err <= target || r >= limit {
                break;
            }
            r *= 2;
        }
    }
    Ok(())
}
