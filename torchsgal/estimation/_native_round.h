/* One Levenberg-Marquardt / Gauss-Newton round's verdict and bookkeeping per problem
 * (torchsgal::lm_round_update, estimation/graph/round_update.py, whose tensor code it follows
 * operation for operation, in the problems' dtype T; included by estimation/_native.c once per
 * element type T with suffix SFX).
 *
 * Pointers: cost, model_cost, new_cost, lin_change, solved (bool), lam, cost_start, iterations
 * (int64), status (int64), then the outputs success (bool), lam, cost_start, iterations and
 * status; params: eps, min_fidelity, lambda_factor,
 * lambda_lower, lambda_upper, judge_tol, error_tol, rel_tol, abs_tol; codes: damped,
 * max_iterations, CONVERGED, MAX_ITERATIONS, DIVERGED.
 */
#define RU_(name, sfx) name##_##sfx
#define RU__(name, sfx) RU_(name, sfx)
#define RU(name) RU__(name, SFX)

static void RU(lm_round_update)(void **p, const double *params, const int64_t *codes, int64_t n) {
    const T *cost = p[0], *model = p[1], *new_cost = p[2], *lin_change = p[3];
    const uint8_t *solved = p[4];
    const T *lam = p[5], *cost_start = p[6];
    const int64_t *iterations = p[7], *status = p[8];
    uint8_t *success_out = p[9];
    T *lam_out = p[10], *cost_start_out = p[11];
    int64_t *iterations_out = p[12], *status_out = p[13];
    const T eps = (T)params[0], min_fidelity = (T)params[1], factor = (T)params[2];
    const T lower = (T)params[3], upper = (T)params[4], judge_tol = (T)params[5];
    const T error_tol = (T)params[6], rel_tol = (T)params[7], abs_tol = (T)params[8];
    const int64_t damped = codes[0], max_iterations = codes[1];
    const int64_t converged_code = codes[2], max_iterations_code = codes[3], diverged_code = codes[4];
    for (int64_t b = 0; b < n; ++b) {
        const T c = cost[b], nc = new_cost[b], dl = lin_change[b];
        int success, gave_up, done;
        T lam_next;
        if (damped) { /* _decide */
            const T dc = c - nc;
            success = solved[b] && dl > eps * model[b] && dc / dl > min_fidelity && isfinite(nc);
            const int valid = solved[b] && dl >= 0;
            const int stop_search = (valid != success) && fabs(dc) < judge_tol * c;
            const T lam_up = lam[b] * factor, lam_down = lam[b] / factor;
            /* clamp_min: NaN stays NaN */
            lam_next = success ? (lam_down < lower ? lower : lam_down) : (stop_search ? lam[b] : lam_up);
            const int settled = success || stop_search;
            done = settled || lam_up >= upper;
            gave_up = done && !settled;
        } else {
            success = solved[b] && isfinite(nc);
            gave_up = !success;
            done = 1;
            lam_next = 0;
        }
        const T accepted = success ? nc : c; /* the cost after the round (_accept) */
        const int64_t it = iterations[b] + success;
        const T decrease = cost_start[b] - accepted; /* _converged */
        const int converged = accepted <= error_tol || decrease <= rel_tol * cost_start[b] ||
                              decrease <= abs_tol;
        /* _round_status */
        int64_t ended = converged ? converged_code : (it >= max_iterations ? max_iterations_code : status[b]);
        if (gave_up) ended = diverged_code;
        success_out[b] = (uint8_t)success;
        lam_out[b] = lam_next;
        iterations_out[b] = it;
        status_out[b] = done ? ended : status[b];
        cost_start_out[b] = done ? accepted : cost_start[b];
    }
}

#undef RU
#undef RU__
#undef RU_
