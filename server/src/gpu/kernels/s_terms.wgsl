// One object's rows of S summed from its radial terms on a translucency change: the
// device's twin of the engine's `ObjectTerms::write` (engine/src/sterms.rs), over the flat
// records of `sterms::FlatTerms`. Four stages, one per pipeline (STAGE):
//   0: each row's values: a direct entry is the sum of its terms under its table (0 where
//      the profile does not reach), a link A_k R(r) (the mean of R at two roots where it
//      has them);
//   1: each column's Σ_j A_j S_ji through the column gather, into sums[i];
//   2: each linked node's e_k = Σ_j A_j R(r_jk) through the node gather, into sums[n + k];
//   3: each row's values times their column's factor (sums[i] for a direct entry,
//      sums[n + k] for a link), the energy bound's factors written over the sums;
//   4: with node rows pushed down to the patches (S on the device is N × (N + M)), each
//      pushed value as the sum of the values it gathers (`push` of `gather`).
// Values are RGB, three f32 each, in the object's own array (its rows of S in S's order).

override STAGE: u32 = 0u;

const OPPOSITE: u32 = 0x80000000u;
const TWO: u32 = 0x40000000u;
const WG: u32 = 64u;

// A profile's table (sterms::FlatTable): its cells from `base` (two vec4 each: the start
// and the rise over the cell; R's N cells, a zero cell, W's N cells, W's total).
struct Table {
    base: u32,
    w_base: u32,
    end: f32,
    r_max: f32,
    scale: f32,
    cells_f: f32,
    _p0: u32,
    _p1: u32,
}

struct Params {
    rows: u32,
    n: u32,
    nodes: u32,
    grid_x: u32,
    // Offsets into `gather`: the column pointers, the node pointers, the column items,
    // the node items (items are (index, area bits) pairs).
    column_ptr: u32,
    node_ptr: u32,
    column_items: u32,
    node_items: u32,
    // The pushed values' pointers and items in `gather`, and their count.
    push_ptr: u32,
    push_items: u32,
    pushed: u32,
    _pad: u32,
    same: Table,
    other: Table,
}

struct Row {
    value: u32,
    e0: u32,
    e1: u32,
    l0: u32,
    l1: u32,
    local: u32,
    area: f32,
    _pad: u32,
}

struct Entry {
    src: u32,
    dist: f32,
    hi_max: f32,
    terms: u32,
}

struct Link {
    root: f32,
    lo: f32,
    hi: f32,
    area: f32,
    node: u32,
    value: u32,
    _p0: u32,
    _p1: u32,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> tables: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> rows: array<Row>;
@group(0) @binding(3) var<storage, read> entries: array<Entry>;
// (√r, negated for W; weight; the cell's lo, hi).
@group(0) @binding(4) var<storage, read> terms: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> links: array<Link>;
@group(0) @binding(6) var<storage, read> gather: array<u32>;
@group(0) @binding(7) var<storage, read_write> sums: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> values: array<f32>;
@group(0) @binding(9) var<storage, read_write> pushed: array<f32>;

fn table(opposite: bool) -> Table {
    if opposite {
        return P.other;
    }
    return P.same;
}

// The function whose cells start at `base` at x = √r × scale (x ≥ 0): past the table, the
// cell after its last (TermTable::cell).
fn cell(t: Table, x_in: f32, base: u32) -> vec3<f32> {
    var x = x_in;
    if !(x < t.cells_f) {
        x = t.cells_f;
    }
    let k = u32(x);
    let f = x - f32(k);
    let c = t.base + 2u * (base + k);
    return tables[c].xyz + f * tables[c + 1u].xyz;
}

fn r_root(t: Table, root: f32) -> vec3<f32> {
    return cell(t, max(root, 0.0) * t.scale, 0u);
}

// A packed term's value (TermTable::sum_packed): W's cells for a negated root.
fn packed(t: Table, term: vec4<f32>) -> vec3<f32> {
    let w = (bitcast<u32>(term.x) >> 31u) * t.w_base;
    return cell(t, abs(term.x) * t.scale, w) * term.y;
}

// An R term whose cell the table ends inside counts the part below the end
// (TermTable::eval).
fn partial(t: Table, term: vec4<f32>) -> vec3<f32> {
    let lo = term.z;
    let hi = term.w;
    if lo >= t.end {
        return vec3<f32>(0.0);
    }
    let f = (t.end * t.end - lo * lo) / (hi * hi - lo * lo);
    return r_root(t, min(abs(term.x), t.end * (1.0 - 1e-6))) * f * term.y;
}

// Entry e's value in a row whose patch is `local` (ObjectTerms::value): 0 where not kept.
fn entry_value(e: u32, local: u32) -> vec3<f32> {
    let ent = entries[e];
    let t = table((ent.terms & OPPOSITE) != 0u);
    let self_term = ent.src == local;
    if !self_term && ent.dist >= t.r_max {
        return vec3<f32>(0.0);
    }
    let t0 = ent.terms & ~OPPOSITE;
    let t1 = entries[e + 1u].terms & ~OPPOSITE;
    var s = vec3<f32>(0.0);
    if ent.hi_max <= t.end {
        for (var k = t0; k < t1; k++) {
            s += packed(t, terms[k]);
        }
    } else {
        for (var k = t0; k < t1; k++) {
            let term = terms[k];
            if term.w <= t.end {
                s += packed(t, term);
            } else {
                s += partial(t, term);
            }
        }
    }
    if self_term || any(s > vec3<f32>(0.0)) {
        return s;
    }
    return vec3<f32>(0.0);
}

// Link l's profile value R (sterms::link_reading): at its two roots' mean while within the
// table, at its root otherwise.
fn link_r(l: u32) -> vec3<f32> {
    let lk = links[l];
    let t = table((lk.node & OPPOSITE) != 0u);
    if (lk.node & TWO) != 0u && lk.root < t.end {
        return (r_root(t, lk.lo) + r_root(t, lk.hi)) * 0.5;
    }
    return r_root(t, lk.root);
}

fn set_value(v: u32, x: vec3<f32>) {
    values[3u * v] = x.x;
    values[3u * v + 1u] = x.y;
    values[3u * v + 2u] = x.z;
}

fn value_at(v: u32) -> vec3<f32> {
    return vec3<f32>(values[3u * v], values[3u * v + 1u], values[3u * v + 2u]);
}

fn write_row(r: u32) {
    let row = rows[r];
    for (var e = row.e0; e < row.e1; e++) {
        set_value(row.value + (e - row.e0), entry_value(e, row.local));
    }
    for (var l = row.l0; l < row.l1; l++) {
        set_value(links[l].value, link_r(l) * links[l].area);
    }
}

fn column_sum(i: u32) {
    var s = vec3<f32>(0.0);
    for (var q = gather[P.column_ptr + i]; q < gather[P.column_ptr + i + 1u]; q++) {
        let at = P.column_items + 2u * q;
        s += bitcast<f32>(gather[at + 1u]) * value_at(gather[at]);
    }
    sums[i] = vec4<f32>(s, 0.0);
}

fn node_sum(k: u32) {
    var s = vec3<f32>(0.0);
    for (var q = gather[P.node_ptr + k]; q < gather[P.node_ptr + k + 1u]; q++) {
        let at = P.node_items + 2u * q;
        s += bitcast<f32>(gather[at + 1u]) * link_r(gather[at]);
    }
    sums[P.n + k] = vec4<f32>(s, 0.0);
}

fn scale_row(r: u32) {
    let row = rows[r];
    for (var e = row.e0; e < row.e1; e++) {
        let v = row.value + (e - row.e0);
        set_value(v, value_at(v) * sums[entries[e].src].xyz);
    }
    for (var l = row.l0; l < row.l1; l++) {
        let k = links[l].node & ~(OPPOSITE | TWO);
        set_value(links[l].value, value_at(links[l].value) * sums[P.n + k].xyz);
    }
}

fn push(e: u32) {
    var s = vec3<f32>(0.0);
    for (var q = gather[P.push_ptr + e]; q < gather[P.push_ptr + e + 1u]; q++) {
        s += value_at(gather[P.push_items + q]);
    }
    pushed[3u * e] = s.x;
    pushed[3u * e + 1u] = s.y;
    pushed[3u * e + 2u] = s.z;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let id = gid.x + gid.y * P.grid_x * WG;
    if STAGE == 0u {
        if id < P.rows {
            write_row(id);
        }
    } else if STAGE == 1u {
        if id < P.n {
            column_sum(id);
        }
    } else if STAGE == 2u {
        if id < P.nodes {
            node_sum(id);
        }
    } else if STAGE == 3u {
        if id < P.rows {
            scale_row(id);
        }
    } else if id < P.pushed {
        push(id);
    }
}
