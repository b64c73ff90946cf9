# The "robot": a two-joint arm on a test rig, simulated here in awk, a program that knows nothing of
# ppprops (robot.toml declares what it sees and does). It reads one trial as `ppprops ask` prints it
# (one JSON line), runs the linear policy u = clip(W^T s + b, -2, 2) for one episode per seed it was
# given, and prints the feedback as one JSON object for `ppprops tell DIR TRIAL --stdin`:
#   {"returns": [...], "components": [{"reward_distance": .., "reward_effort": ..}, ...],
#    "diagnostics": [{"final_distance": .., "reached": ..}, ...]}
#
# The rig: links of 0.30 m and 0.25 m, joint inertias 0.05 and 0.02 kg m^2, viscous damping 0.5/s,
# steps of 10 ms, 200 steps per trial; the target is drawn from the episode's seed anywhere between
# 0.15 m and 0.5 m from the shoulder. Each step pays -distance - 0.01 (u1^2 + u2^2).
#
#   ppprops ask DIR | awk -f rig_arm.awk | ppprops tell DIR TRIAL --stdin

function list(key,    s, start) {
    if (!match($0, "\"" key "\": \\[[^]]*\\]")) { print "rig_arm: no " key " in the trial" > "/dev/stderr"; exit 2 }
    s = substr($0, RSTART, RLENGTH)
    start = index(s, "[")
    return substr(s, start + 1, length(s) - start - 1)
}

function clip(u) { return u > 2 ? 2 : (u < -2 ? -2 : u) }

{
    if (split(list("theta"), theta, /, */) != 14) { print "rig_arm: expected 14 parameters" > "/dev/stderr"; exit 2 }
    n_seeds = split(list("seeds"), seeds, /, */)
    returns = ""; comps = ""; diags = ""
    for (e = 1; e <= n_seeds; e++) {
        srand(seeds[e] % 2147483647)
        r = 0.15 + 0.35 * rand(); phi = 6.283185307 * rand()
        tx = r * cos(phi); ty = r * sin(phi)
        q1 = 0; q2 = 0; w1 = 0; w2 = 0; dist_sum = 0; effort_sum = 0
        for (t = 0; t < 200; t++) {
            dx = tx - (0.30 * cos(q1) + 0.25 * cos(q1 + q2))
            dy = ty - (0.30 * sin(q1) + 0.25 * sin(q1 + q2))
            s[1] = q1; s[2] = q2; s[3] = w1; s[4] = w2; s[5] = dx; s[6] = dy
            for (j = 1; j <= 2; j++) {          # theta[i*2 + j] = W[i][j] (1-based here), then b
                u[j] = theta[12 + j]
                for (i = 1; i <= 6; i++) u[j] += s[i] * theta[(i - 1) * 2 + j]
                u[j] = clip(u[j])
            }
            dist = sqrt(dx * dx + dy * dy)
            dist_sum -= dist; effort_sum -= 0.01 * (u[1] * u[1] + u[2] * u[2])
            w1 += 0.01 * (u[1] / 0.05 - 0.5 * w1); w2 += 0.01 * (u[2] / 0.02 - 0.5 * w2)
            q1 += 0.01 * w1; q2 += 0.01 * w2
        }
        dx = tx - (0.30 * cos(q1) + 0.25 * cos(q1 + q2)); dy = ty - (0.30 * sin(q1) + 0.25 * sin(q1 + q2))
        final = sqrt(dx * dx + dy * dy)
        sep = e > 1 ? ", " : ""
        returns = returns sep sprintf("%.6f", dist_sum + effort_sum)
        comps = comps sep sprintf("{\"reward_distance\": %.6f, \"reward_effort\": %.6f}", dist_sum, effort_sum)
        diags = diags sep sprintf("{\"final_distance\": %.6f, \"reached\": %d}", final, final < 0.01)
    }
    printf "{\"returns\": [%s], \"components\": [%s], \"diagnostics\": [%s]}\n", returns, comps, diags
}
