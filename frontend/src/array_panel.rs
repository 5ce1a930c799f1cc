//! The page of an array run (issue 24): the overview — a tile per cell (in
//! band or not, in colour and words; t_sr and w against their targets; the
//! lab time) and the heat map of the learned |Jacobian| with the prior's
//! blocks outlined — and, after a click on a tile, that cell's charts (the
//! single-cell [`Dashboard`] over the cell's history,
//! [`crate::cell_history`]) with a way back. The numbers come from
//! [`crate::array_view`], the colours from [`crate::heat_scale`].
//!
//! Test hooks: `data-testid=array-overview` (`data-cells`), `cell-layout`
//! (a ladder's rows and columns, in words), the tiles' grid `.cell-tiles`
//! (`data-rows`: 2 for a ladder, else 1), `cell-tile`
//! (`data-cell`, `data-band` = in / out / unknown), `jacobian-heatmap` (an
//! SVG with `data-rows`, `data-cols`, `data-iteration`, `data-unit`; its
//! elements `.hm-cell` with `data-row`, `data-col`, `data-prior`,
//! `data-value`; the outlines `.hm-block` with `data-prior`), `cell-view`
//! (`data-cell`) and `cell-back`.

use leptos::prelude::*;
use spintune::description::layout::{CellGrid, Layout};
use spintune::protocol::RunStatus;

use crate::array_view::{cell_runs, heat_map, tiles, Band, HeatMap, Prior, Tile};
use crate::cell_history;
use crate::charts::num_label;
use crate::heat_scale::{power_label, LogScale};
use crate::history::RunHistory;
use crate::ui::{Dashboard, DashboardHooks};

/// An array run: the overview, or one cell's charts.
#[component]
pub fn ArrayOverview(
    /// The whole run's history.
    history: RwSignal<RunHistory>,
    /// The run's status (for the cell charts' tuned badge).
    #[prop(optional)]
    status: Option<Signal<Option<RunStatus>>>,
    /// How the cells sit, if known: a ladder's tiles in its two rows
    /// (cells numbered row by row); unknown or a chain, one wrapping row.
    #[prop(optional, into)]
    grid: Option<Signal<Option<CellGrid>>>,
) -> impl IntoView {
    let ladder = Memo::new(move |_| {
        grid.and_then(|g| g.get())
            .filter(|g| g.layout() == Layout::Ladder)
            .map(|g| (g.rows(), g.columns()))
    });
    let selected = RwSignal::new(None::<u32>);
    let latest = Memo::new(move |_| history.with(|h| h.latest().cloned()));
    let tiles = Memo::new(move |_| latest.with(|r| r.as_ref().map(tiles).unwrap_or_default()));
    let heat = Memo::new(move |_| latest.with(|r| r.as_ref().and_then(heat_map)));
    // Tiles keyed by cell: a tile's button stays while its numbers change
    // (a click during a live run is not lost to a re-render).
    let cells = Memo::new(move |_| tiles.with(|t| t.iter().map(|t| t.cell).collect::<Vec<_>>()));
    move || {
        match selected.get() {
        None => view! {
            <section class="array-overview" data-testid="array-overview"
                data-cells=move || cells.with(|c| c.len().to_string())>
                <h3>"Cells " <small>"(in band: t_sr and w both within target ± tolerance; click a cell for its charts)"</small></h3>
                {move || ladder.get().map(|(rows, columns)| view! {
                    <p class="hint" data-testid="cell-layout">{format!("ladder: {rows} rows of {columns} cells, numbered row by row; a cell's neighbours are beside it and across the rung")}</p>
                })}
                <div class="cell-tiles"
                    data-rows=move || ladder.get().map_or(1, |(r, _)| r).to_string()
                    style:grid-template-columns=move || ladder.get().map(|(_, c)| format!("repeat({c}, minmax(150px, 1fr))")).unwrap_or_default()>
                    <For each=move || cells.get() key=|c| *c
                        children=move |cell| {
                            let t = Memo::new(move |_| tiles.with(|ts| ts.iter().find(|t| t.cell == cell).cloned()));
                            view! { <CellTile tile=t cell selected /> }
                        }
                    />
                </div>
                {move || heat.get().map(|h| view! { <JacobianHeatMap map=h /> })}
            </section>
        }
        .into_any(),
        Some(cell) => view! {
            <CellView history cell status back=Callback::new(move |_| selected.set(None)) />
        }
        .into_any(),
    }
    }
}

/// One cell's tile: a button that opens its charts.
#[component]
fn CellTile(tile: Memo<Option<Tile>>, cell: u32, selected: RwSignal<Option<u32>>) -> impl IntoView {
    let band = move || tile.with(|t| t.as_ref().map_or(Band::Unknown, |t| t.band));
    let mark = move || match band() {
        Band::In => "✓",
        Band::Out => "✗",
        Band::Unknown => "?",
    };
    view! {
        <button
            class=move || format!("cell-tile band-{}", band().name())
            data-testid="cell-tile"
            data-cell=cell
            data-band=move || band().name()
            title=format!("show cell {cell}'s charts")
            on:click=move |_| selected.set(Some(cell))
        >
            <span class="cell-name">{format!("cell {cell}")}</span>
            <span class="cell-band" data-testid="cell-band">{move || format!("{} {}", mark(), band().label())}</span>
            {move || tile.with(|t| t.as_ref().map(|t| {
                let params = t.parameters.iter().map(|p| view! {
                    <span class="cell-param" data-parameter=p.name.clone()
                        data-in-band=p.in_band.map_or("unknown", |b| if b { "true" } else { "false" })>
                        <i>{p.name.clone()}</i>" "{p.text()}
                    </span>
                }).collect_view();
                view! {
                    {params}
                    <span class="cell-lab">{format!("lab time {:.1} min", t.lab_minutes)}</span>
                }
            }))}
        </button>
    }
}

/// Geometry of the heat map's SVG (user units = CSS px at full size).
struct Geometry {
    /// Left margin (row labels).
    left: f64,
    /// Top margin (cell and gate labels).
    top: f64,
    /// Element width and height.
    cw: f64,
    ch: f64,
}

impl Geometry {
    fn of(map: &HeatMap) -> Self {
        let cols = map.cols.len().max(1) as f64;
        Self {
            left: 78.0,
            top: 44.0,
            cw: (720.0 / cols).clamp(14.0, 52.0),
            ch: 28.0,
        }
    }

    fn x(&self, c: usize) -> f64 {
        self.left + c as f64 * self.cw
    }

    fn y(&self, r: usize) -> f64 {
        self.top + r as f64 * self.ch
    }
}

/// The learned |Jacobian| (rows parameters, columns gates, colour
/// |∂ln p/∂V| on a log scale in 1/mV) with the prior's own-cell blocks
/// (solid) and nearest-neighbour blocks (dashed) outlined.
#[component]
fn JacobianHeatMap(map: HeatMap) -> impl IntoView {
    let g = Geometry::of(&map);
    let (nr, nc) = (map.rows.len(), map.cols.len());
    let scale = LogScale::for_max(map.max());
    let unit = map.unit.clone();
    let (w_map, h_map) = (nc as f64 * g.cw, nr as f64 * g.ch);
    // colour bar right of the map
    let bar_x = g.left + w_map + 28.0;
    let bar_h = h_map.max(120.0);
    let width = bar_x + 90.0;
    let height = g.top + bar_h + 44.0;
    let cells = (0..nr)
        .flat_map(|r| (0..nc).map(move |c| (r, c)))
        .map(|(r, c)| {
            let v = map.values[r][c];
            let prior = map.prior(r, c);
            let tip = if v.is_finite() {
                format!(
                    "|∂ln {}/∂V_{}| = {} {unit} ({})",
                    map.rows[r],
                    map.cols[c],
                    num_label(&v),
                    prior_words(prior)
                )
            } else {
                format!("∂ln {}/∂V_{}: no estimate", map.rows[r], map.cols[c])
            };
            view! {
                <rect class="hm-cell" x=g.x(c) y=g.y(r) width=g.cw height=g.ch
                    fill=scale.colour(v) data-row=r data-col=c data-col-name=map.cols[c].clone()
                    data-prior=prior.name() data-value=v.to_string()>
                    <title>{tip}</title>
                </rect>
            }
        })
        .collect_view();
    let blocks = map
        .blocks()
        .into_iter()
        .map(|b| {
            let own = b.prior == Prior::Own;
            view! {
                <rect class=if own { "hm-block own" } else { "hm-block neighbour" }
                    data-prior=b.prior.name()
                    x=g.x(b.col0) + 1.0 y=g.y(b.row0) + 1.0
                    width=b.cols as f64 * g.cw - 2.0 height=b.rows as f64 * g.ch - 2.0
                    fill="none" stroke=if own { "currentColor" } else { "#d55e00" }
                    stroke-width=if own { "2.5" } else { "1.5" }
                    stroke-dasharray=if own { "none" } else { "5 3" } />
            }
        })
        .collect_view();
    // column labels: the cell above its gates, the gate's own name per column
    let groups = cell_runs(&map.col_cells)
        .into_iter()
        .map(|(cell, c0, n)| {
            let x = g.x(c0) + n as f64 * g.cw / 2.0;
            view! { <text class="hm-label" x=x y=14 text-anchor="middle">{format!("cell {cell}")}</text> }
        })
        .collect_view();
    let gate_labels = (0..nc)
        .map(|c| {
            let name = spintune::sim::array::split_gate(&map.cols[c])
                .map_or(map.cols[c].clone(), |(_, l)| l.to_string());
            view! { <text class="hm-label small" x=g.x(c) + g.cw / 2.0 y=g.top - 8.0 text-anchor="middle">{name}</text> }
        })
        .collect_view();
    let row_labels = (0..nr)
        .map(|r| view! {
            <text class="hm-label" x=g.left - 6.0 y=g.y(r) + g.ch / 2.0 + 4.0 text-anchor="end">{map.rows[r].clone()}</text>
        })
        .collect_view();
    // the colour bar: 40 steps, ticks at the powers of ten
    let steps = 40;
    let bar = (0..steps)
        .map(|i| {
            let f = (i as f64 + 0.5) / steps as f64;
            let v = scale.lo * (scale.hi / scale.lo).powf(f);
            let y = g.top + bar_h * (1.0 - (i + 1) as f64 / steps as f64);
            view! { <rect x=bar_x y=y width=16 height=bar_h / steps as f64 + 0.5 fill=scale.colour(v) /> }
        })
        .collect_view();
    let ticks = scale
        .ticks()
        .into_iter()
        .map(|t| {
            let y = g.top + bar_h * (1.0 - scale.fraction(t).unwrap_or(0.0));
            view! {
                <line x1=bar_x + 16.0 x2=bar_x + 20.0 y1=y y2=y stroke="currentColor" />
                <text class="hm-label small" x=bar_x + 23.0 y=y + 4.0>{power_label(t)}</text>
            }
        })
        .collect_view();
    let axis_y = g.top + h_map + 20.0;
    let own_max = map.max_where(Prior::Own);
    let nb_max = map.max_where(Prior::Neighbour);
    let out_max = map.max_where(Prior::Outside);
    let fmt = |v: f64| {
        if v.is_finite() {
            format!("{} {}", num_label(&v), map.unit)
        } else {
            "–".to_string()
        }
    };
    let share = if own_max.is_finite() && nb_max.is_finite() && own_max > 0.0 {
        format!(" ({:.0} % of own)", 100.0 * nb_max / own_max)
    } else {
        String::new()
    };
    let summary = format!(
        "Largest |∂ln p/∂V|: own cell {} · nearest neighbours {}{share} · beyond (the prior says 0) {}",
        fmt(own_max),
        fmt(nb_max),
        fmt(out_max)
    );
    view! {
        <div class="heatmap-box">
            <h3>"Learned |Jacobian| " <small>{format!("|∂ln p/∂V| in {} at iteration {}", map.unit, map.iteration)}</small></h3>
            <p class="hint">"How much each parameter (row; its logarithm: 0.01 /mV is about 1 % per mV) moves with each gate's voltage (column, V in mV), as the filter has learned it. Outlined: where the prior expects it — a cell's own gates (solid) and its nearest neighbours' (dashed); beyond them the prior says zero."</p>
            <div class="heatmap-scroll">
            <svg class="heatmap" data-testid="jacobian-heatmap"
                data-rows=nr data-cols=nc data-iteration=map.iteration data-unit=map.unit.clone()
                data-scale-lo=scale.lo data-scale-hi=scale.hi
                viewBox=format!("0 0 {width:.0} {height:.0}")
                width=format!("{width:.0}") style=format!("max-width:100%;height:auto")
                role="img" aria-label=format!("learned |Jacobian|, {nr} parameters × {nc} gates, {}", map.unit)>
                {groups}
                {gate_labels}
                {row_labels}
                {cells}
                {blocks}
                <text class="hm-label small" x=g.left + w_map / 2.0 y=axis_y text-anchor="middle">"gate (∂/∂V, V in mV)"</text>
                <text class="hm-label small" x=12 y=g.top + h_map / 2.0 text-anchor="middle"
                    transform=format!("rotate(-90 12 {:.1})", g.top + h_map / 2.0)>"parameter p (ln p)"</text>
                {bar}
                {ticks}
                <text class="hm-label small" x=bar_x y=14>"|∂ln p/∂V|"</text>
                <text class="hm-label small" x=bar_x y=g.top - 8.0>{format!("{unit}, log")}</text>
            </svg>
            </div>
            <div class="legend">
                <span><i class="swatch hm-own"></i>"own cell's gates (prior)"</span>
                <span><i class="swatch hm-neighbour"></i>"nearest neighbours' gates (prior)"</span>
                <span><i class="swatch" style=format!("background:{}", crate::heat_scale::MISSING)></i>"no estimate"</span>
                <span>{format!("colour: below {} {} is the lightest", power_label(scale.lo), map.unit)}</span>
            </div>
            <p class="hm-summary" data-testid="heatmap-summary">{summary}</p>
        </div>
    }
}

fn prior_words(p: Prior) -> &'static str {
    match p {
        Prior::Own => "own cell",
        Prior::Neighbour => "nearest neighbour",
        Prior::Outside => "beyond the neighbours: the prior says 0",
    }
}

/// One cell's charts, following the run.
#[component]
fn CellView(
    history: RwSignal<RunHistory>,
    cell: u32,
    status: Option<Signal<Option<RunStatus>>>,
    back: Callback<()>,
) -> impl IntoView {
    let mut first = RunHistory::new();
    history.with_untracked(|full| cell_history::sync(full, cell, &mut first));
    let cell_h = RwSignal::new(first);
    Effect::new(move |_| {
        history.with(|full| {
            cell_h.try_maybe_update(|c| {
                let before = c.version();
                cell_history::sync(full, cell, c);
                (c.version() != before, ())
            })
        });
    });
    let band = Memo::new(move |_| {
        history.with(|h| {
            h.latest()
                .and_then(|r| tiles(r).into_iter().find(|t| t.cell == cell))
                .map(|t| t.band)
        })
    });
    let hooks = DashboardHooks {
        want_scans: None,
        status,
    };
    view! {
        <section class="cell-view" data-testid="cell-view" data-cell=cell>
            <div class="cell-head">
                <button data-testid="cell-back" on:click=move |_| back.run(())>"← all cells"</button>
                <h3>{format!("Cell {cell}")}</h3>
                {move || band.get().map(|b| view! {
                    <span class=format!("badge band-{}", b.name()) data-testid="cell-view-band">{b.label()}</span>
                })}
            </div>
            <p class="hint">{format!("Cell {cell}'s parameters, its learned gradient rows over its own gates (1/mV: log space) and its gate voltages, as a single double dot. The crosstalk onto its neighbours' gates is in the overview's heat map; lab time and failed fits are the array's.")}</p>
            <Dashboard history=cell_h hooks=hooks />
        </section>
    }
}
