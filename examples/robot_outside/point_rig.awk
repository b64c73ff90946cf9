# A "robot" that knows nothing of ppprops: a point mass on a rail, pushed by a motor.
#
# Reads one trial as `ppprops ask` prints it (one JSON line), runs the linear policy
# u = clip(w_x * x + w_v * v + b, -1, 1) for one episode per seed it was given, and prints the
# feedback as one JSON object for `ppprops tell DIR TRIAL --stdin`:
#   {"returns": [...], "components": [{"distance_cost": .., "effort_cost": ..}, ...],
#    "diagnostics": [{"final_distance": ..}, ...]}
# The rail: x' = v, v' = u - 0.5 v (friction), dt = 0.05 s, 120 steps, start x0 uniform in [-1, 1]
# from the episode's seed, v0 = 0. Reward per step: -x^2 (distance cost) - 0.1 u^2 (effort cost).
#
#   ppprops ask DIR | awk -f point_rig.awk | ppprops tell DIR TRIAL --stdin

function list(key,    s, start) {
    if (!match($0, "\"" key "\": \\[[^]]*\\]")) { print "point_rig: no " key " in the trial" > "/dev/stderr"; exit 2 }
    s = substr($0, RSTART, RLENGTH)
    start = index(s, "[")
    return substr(s, start + 1, length(s) - start - 1)
}

function clip(u) { return u > 1 ? 1 : (u < -1 ? -1 : u) }

{
    n_theta = split(list("theta"), theta, /, */)
    if (n_theta != 3) { print "point_rig: expected 3 parameters (w_x, w_v, b), got " n_theta > "/dev/stderr"; exit 2 }
    n_seeds = split(list("seeds"), seeds, /, */)
    returns = ""; comps = ""; diags = ""
    for (e = 1; e <= n_seeds; e++) {
        srand(seeds[e] % 2147483647)
        x = 2 * rand() - 1; v = 0; dist = 0; effort = 0
        for (t = 0; t < 120; t++) {
            u = clip(theta[1] * x + theta[2] * v + theta[3])
            dist -= x * x; effort -= 0.1 * u * u
            v += 0.05 * (u - 0.5 * v)
            x += 0.05 * v
        }
        fx = x < 0 ? -x : x
        sep = e > 1 ? ", " : ""
        returns = returns sep sprintf("%.6f", dist + effort)
        comps = comps sep sprintf("{\"distance_cost\": %.6f, \"effort_cost\": %.6f}", dist, effort)
        diags = diags sep sprintf("{\"final_distance\": %.6f}", fx)
    }
    printf "{\"returns\": [%s], \"components\": [%s], \"diagnostics\": [%s]}\n", returns, comps, diags
}
