/* main.c - example program of the exported volcal solver volcal_xfyz.
 *
 *   volcal_xfyz_example MEASUREMENTS.csv OUTDIR [POSES.csv]
 *
 * Reads a measurement table (volcal's format: station, point, one column per axis in mm /
 * deg, optional tool_x, tool_y, tool_z in mm, length in mm, optional sigma in mm; other
 * columns are ignored), matches every row to the exported plan by (station, point), runs
 * volcal_xfyz_identify and writes to OUTDIR (created if needed):
 *   parameters.csv  name, value, unit (um / urad)
 *   stations.csv    station, x_mm, y_mm, z_mm, dead_length_mm
 *   residuals.csv   station, point, residual_um (model - measured)
 *   volumetric.csv  axis columns, tool_x, tool_y, tool_z, dx_um, dy_um, dz_um at the poses
 *                   of POSES.csv, or else at every distinct point of the measurement
 *   status.txt      converged, status, iterations, KKT residual, ... (key = value)
 * Exit code: 0 converged, 1 not converged (the files are written, flagged in status.txt),
 * 2 bad input.  Needs POSIX (strdup, mkdir) besides C99.
 */
#define _POSIX_C_SOURCE 200809L
#include "volcal_xfyz.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/types.h>

#define N VOLCAL_XFYZ_N_READINGS
#define NA VOLCAL_XFYZ_N_AXES

#define MAX_LINE 65536
#define MAX_FIELDS 512

/* strip blanks, line ends and surrounding double quotes (in place) */
static char *trim(char *s) {
  char *e;
  while (*s == ' ' || *s == '\t' || *s == '\r' || *s == '\n') ++s;
  e = s + strlen(s);
  while (e > s && (e[-1] == ' ' || e[-1] == '\t' || e[-1] == '\r' || e[-1] == '\n')) *--e = 0;
  if (e - s >= 2 && s[0] == '"' && e[-1] == '"') {
    e[-1] = 0;
    ++s;
  }
  return s;
}

/* split a line at commas (no quoted commas) */
static int split(char *line, char **f, int max) {
  int n = 0;
  char *p = line;
  for (;;) {
    char *c = strchr(p, ',');
    if (n == max) return -1;
    if (c) *c = 0;
    f[n++] = trim(p);
    if (!c) break;
    p = c + 1;
  }
  return n;
}

/* index of column a (or its synonym b) in the header, -1 when absent */
static int column(char **hdr, int n, const char *a, const char *b) {
  int k;
  for (k = 0; k < n; ++k)
    if (!strcmp(hdr[k], a) || (b && !strcmp(hdr[k], b))) return k;
  return -1;
}

/* a number; an empty field or "nan" gives NaN when allow_empty, else an error */
static int number(const char *s, double *v, int allow_empty) {
  char *end;
  if (!*s || !strcmp(s, "nan") || !strcmp(s, "NaN") || !strcmp(s, "NA")) {
    *v = NAN;
    return allow_empty ? 0 : -1;
  }
  *v = strtod(s, &end);
  return (*trim(end) == 0) ? 0 : -1;
}

static int is_blank(const char *s) {
  for (; *s; ++s)
    if (*s != ' ' && *s != '\t' && *s != '\r' && *s != '\n' && *s != ',') return 0;
  return 1;
}

/* column of axis a: "X" or "X_mm" (linear) / "X_deg" (rotary) */
static int axis_column(char **hdr, int n, int a) {
  char syn[64];
  snprintf(syn, sizeof syn, "%s_%s", volcal_xfyz_axis_names[a], volcal_xfyz_axis_rotary[a] ? "deg" : "mm");
  return column(hdr, n, volcal_xfyz_axis_names[a], syn);
}

/* poses of a CSV with axis columns and optional tool columns; returns the count or -1 */
static int read_poses(const char *path, double **q, double **tool) {
  static char line[MAX_LINE];
  char *hdr_buf, *f[MAX_FIELDS], *h[MAX_FIELDS];
  int nh, col[VOLCAL_XFYZ_N_AXES], tcol[3], a, n = 0, cap = 256, row = 1;
  static const char *tn[3] = {"tool_x", "tool_y", "tool_z"};
  static const char *ts[3] = {"tool_x_mm", "tool_y_mm", "tool_z_mm"};
  FILE *in = fopen(path, "r");
  if (!in) {
    fprintf(stderr, "%s: cannot open\n", path);
    return -1;
  }
  if (!fgets(line, sizeof line, in)) {
    fprintf(stderr, "%s: empty file\n", path);
    fclose(in);
    return -1;
  }
  hdr_buf = strdup(line[0] == '\xef' ? line + 3 : line);
  nh = split(hdr_buf, h, MAX_FIELDS);
  for (a = 0; a < VOLCAL_XFYZ_N_AXES; ++a) {
    col[a] = axis_column(h, nh, a);
    if (col[a] < 0) {
      fprintf(stderr, "%s: missing axis column '%s'\n", path, volcal_xfyz_axis_names[a]);
      fclose(in);
      free(hdr_buf);
      return -1;
    }
  }
  for (a = 0; a < 3; ++a) tcol[a] = column(h, nh, tn[a], ts[a]);
  *q = (double *)malloc(sizeof(double) * cap * VOLCAL_XFYZ_N_AXES);
  *tool = (double *)malloc(sizeof(double) * cap * 3);
  while (fgets(line, sizeof line, in)) {
    int nf;
    ++row;
    if (is_blank(line)) continue;
    nf = split(line, f, MAX_FIELDS);
    if (n == cap) {
      cap *= 2;
      *q = (double *)realloc(*q, sizeof(double) * cap * VOLCAL_XFYZ_N_AXES);
      *tool = (double *)realloc(*tool, sizeof(double) * cap * 3);
    }
    for (a = 0; a < VOLCAL_XFYZ_N_AXES; ++a)
      if (col[a] >= nf || number(f[col[a]], &(*q)[n * VOLCAL_XFYZ_N_AXES + a], 0)) {
        fprintf(stderr, "%s, row %d: bad value of %s\n", path, row, volcal_xfyz_axis_names[a]);
        fclose(in);
        free(hdr_buf);
        return -1;
      }
    for (a = 0; a < 3; ++a) {
      double v = 0.0;
      if (tcol[a] >= 0 && (tcol[a] >= nf || number(f[tcol[a]], &v, 0))) {
        fprintf(stderr, "%s, row %d: bad value of %s\n", path, row, tn[a]);
        fclose(in);
        free(hdr_buf);
        return -1;
      }
      (*tool)[n * 3 + a] = v;
    }
    ++n;
  }
  fclose(in);
  free(hdr_buf);
  return n;
}

/* volumetric errors (um) at poses, with the axis and tool columns in front */
static int write_volumetric(FILE *out, int n, const double *q, const double *tool,
                            const double *theta) {
  int i, a;
  for (a = 0; a < VOLCAL_XFYZ_N_AXES; ++a) fprintf(out, "%s,", volcal_xfyz_axis_names[a]);
  fprintf(out, "tool_x,tool_y,tool_z,dx_um,dy_um,dz_um\n");
  for (i = 0; i < n; ++i) {
    double dp[3];
    if (volcal_xfyz_volumetric(q + i * VOLCAL_XFYZ_N_AXES, tool + 3 * i, theta, NULL, dp, NULL, NULL))
      return -1;
    for (a = 0; a < VOLCAL_XFYZ_N_AXES; ++a) fprintf(out, "%.17g,", q[i * VOLCAL_XFYZ_N_AXES + a]);
    fprintf(out, "%.17g,%.17g,%.17g,%.17g,%.17g,%.17g\n", tool[3 * i], tool[3 * i + 1],
            tool[3 * i + 2], dp[0] * 1e3, dp[1] * 1e3, dp[2] * 1e3);
  }
  return 0;
}

typedef struct {
  const char *station, *point;
  int index;
} plan_key;

static int key_cmp(const void *a, const void *b) {
  const plan_key *x = (const plan_key *)a, *y = (const plan_key *)b;
  int c = strcmp(x->station, y->station);
  return c ? c : strcmp(x->point, y->point);
}

static int idx_point_cmp(const void *a, const void *b) {
  int i = *(const int *)a, j = *(const int *)b;
  int c = strcmp(volcal_xfyz_reading_point[i], volcal_xfyz_reading_point[j]);
  return c ? c : (i > j) - (i < j);
}

static FILE *open_out(const char *dir, const char *name) {
  char path[4096];
  FILE *f;
  snprintf(path, sizeof path, "%s/%s", dir, name);
  f = fopen(path, "w");
  if (!f) fprintf(stderr, "cannot write %s\n", path);
  return f;
}

static int int_cmp(const void *a, const void *b) {
  int i = *(const int *)a, j = *(const int *)b;
  return (i > j) - (i < j);
}

static volcal_xfyz_result result;  /* large: keep it off the stack */
static double q[N * NA], tool[N * 3], length[N], sigma[N];
static int seen[N];
static plan_key keys[N];

int main(int argc, char **argv) {
  static char line[MAX_LINE];
  char *h[MAX_FIELDS], *f[MAX_FIELDS], *hdr_buf;
  int nh, col_st, col_pt, col_len, col_sig, col_ax[NA], col_tool[3], a, i, k, row = 1, n = 0;
  static const char *tn[3] = {"tool_x", "tool_y", "tool_z"};
  static const char *ts[3] = {"tool_x_mm", "tool_y_mm", "tool_z_mm"};
  const char *dir;
  FILE *in, *out;
  int status;

  if (argc < 3 || argc > 4) {
    fprintf(stderr, "usage: %s MEASUREMENTS.csv OUTDIR [POSES.csv]\n", argv[0]);
    return 2;
  }
  dir = argv[2];
  in = fopen(argv[1], "r");
  if (!in) {
    fprintf(stderr, "%s: cannot open\n", argv[1]);
    return 2;
  }
  if (!fgets(line, sizeof line, in)) {
    fprintf(stderr, "%s: empty file\n", argv[1]);
    return 2;
  }
  hdr_buf = strdup(line[0] == '\xef' ? line + 3 : line);  /* skip a UTF-8 BOM */
  nh = split(hdr_buf, h, MAX_FIELDS);
  col_st = column(h, nh, "station", NULL);
  col_pt = column(h, nh, "point", NULL);
  col_len = column(h, nh, "length", "length_mm");
  col_sig = column(h, nh, "sigma", "sigma_mm");
  for (a = 0; a < NA; ++a) col_ax[a] = axis_column(h, nh, a);
  for (a = 0; a < 3; ++a) col_tool[a] = column(h, nh, tn[a], ts[a]);
  if (col_st < 0 || col_pt < 0 || col_len < 0) {
    fprintf(stderr, "%s: the header needs station, point and length columns\n", argv[1]);
    return 2;
  }
  for (a = 0; a < NA; ++a)
    if (col_ax[a] < 0) {
      fprintf(stderr, "%s: missing axis column '%s'\n", argv[1], volcal_xfyz_axis_names[a]);
      return 2;
    }

  for (i = 0; i < N; ++i) {
    keys[i].station = volcal_xfyz_station_ids[volcal_xfyz_reading_station[i]];
    keys[i].point = volcal_xfyz_reading_point[i];
    keys[i].index = i;
  }
  if (volcal_xfyz_plan_keys_unique) qsort(keys, N, sizeof keys[0], key_cmp);

  while (fgets(line, sizeof line, in)) {
    int nf;
    plan_key key, *hit;
    ++row;
    if (is_blank(line)) continue;
    nf = split(line, f, MAX_FIELDS);
    if (nf <= col_st || nf <= col_pt || nf <= col_len) {
      fprintf(stderr, "%s, row %d: too few fields\n", argv[1], row);
      return 2;
    }
    key.station = f[col_st];
    key.point = f[col_pt];
    if (volcal_xfyz_plan_keys_unique) {
      hit = (plan_key *)bsearch(&key, keys, N, sizeof keys[0], key_cmp);
    } else {  /* rows must come in plan order */
      hit = (n < N && !strcmp(keys[n].station, key.station) && !strcmp(keys[n].point, key.point))
            ? &keys[n] : NULL;
    }
    if (!hit) {
      fprintf(stderr, "%s, row %d: station '%s', point '%s' is not a reading of the exported "
              "plan (see plan.csv)\n", argv[1], row, key.station, key.point);
      return 2;
    }
    i = hit->index;
    if (seen[i]) {
      fprintf(stderr, "%s, row %d: station '%s', point '%s' appears twice\n", argv[1], row,
              key.station, key.point);
      return 2;
    }
    seen[i] = 1;
    ++n;
    for (a = 0; a < NA; ++a)
      if (col_ax[a] >= nf || number(f[col_ax[a]], &q[i * NA + a], 0)) {
        fprintf(stderr, "%s, row %d: bad value of %s\n", argv[1], row, volcal_xfyz_axis_names[a]);
        return 2;
      }
    for (a = 0; a < 3; ++a) {
      tool[3 * i + a] = 0.0;
      if (col_tool[a] >= 0 && (col_tool[a] >= nf || number(f[col_tool[a]], &tool[3 * i + a], 0))) {
        fprintf(stderr, "%s, row %d: bad value of %s\n", argv[1], row, tn[a]);
        return 2;
      }
    }
    if (number(f[col_len], &length[i], 0)) {
      fprintf(stderr, "%s, row %d: bad length '%s'\n", argv[1], row, f[col_len]);
      return 2;
    }
    sigma[i] = NAN;
    if (col_sig >= 0 && col_sig < nf && number(f[col_sig], &sigma[i], 1)) {
      fprintf(stderr, "%s, row %d: bad sigma '%s'\n", argv[1], row, f[col_sig]);
      return 2;
    }
  }
  fclose(in);
  free(hdr_buf);
  if (n != N) {
    for (i = 0; i < N && seen[i]; ++i) {}
    fprintf(stderr, "%s: %d readings, the exported plan has %d (first missing: station '%s', "
            "point '%s')\n", argv[1], n, N, volcal_xfyz_station_ids[volcal_xfyz_reading_station[i]],
            volcal_xfyz_reading_point[i]);
    return 2;
  }

  status = volcal_xfyz_identify(q, tool, length, sigma, NULL, NULL, NULL, NULL, &result);

  if (mkdir(dir, 0777) && errno != EEXIST) {
    fprintf(stderr, "cannot create %s\n", dir);
    return 2;
  }
  if (!(out = open_out(dir, "status.txt"))) return 2;
  fprintf(out, "converged = %d\nstatus = %d\nstatus_text = %s\nphase = %d\niterations = %d\n"
          "kkt = %.6e\nkkt_rel = %.6e\nstep = %.6e\nconstraint_violation = %.6e\n"
          "cost = %.17g\nchi2_per_dof = %.17g\ndof = %d\n", result.converged, result.status,
          volcal_xfyz_status_string(result.status), result.phase, result.iterations, result.kkt,
          result.kkt_rel, result.step, result.constraint_violation, result.cost,
          result.chi2_per_dof, result.dof);
  fclose(out);

  if (!(out = open_out(dir, "parameters.csv"))) return 2;
  fprintf(out, "name,value,unit\n");
  for (k = 0; k < VOLCAL_XFYZ_N_PARAMS; ++k) {
    int mm = !strcmp(volcal_xfyz_param_units[k], "mm");
    fprintf(out, "%s,%.17g,%s\n", volcal_xfyz_param_names[k], result.theta[k] * (mm ? 1e3 : 1e6),
            mm ? "um" : "urad");
  }
  fclose(out);

  if (!(out = open_out(dir, "stations.csv"))) return 2;
  fprintf(out, "station,x_mm,y_mm,z_mm,dead_length_mm\n");
  for (k = 0; k < VOLCAL_XFYZ_N_STATIONS; ++k)
    fprintf(out, "%s,%.17g,%.17g,%.17g,%.17g\n", volcal_xfyz_station_ids[k], result.stations[k][0],
            result.stations[k][1], result.stations[k][2], result.stations[k][3]);
  fclose(out);

  if (!(out = open_out(dir, "residuals.csv"))) return 2;
  fprintf(out, "station,point,residual_um,sigma_um\n");
  for (i = 0; i < N; ++i)
    fprintf(out, "%s,%s,%.17g,%.17g\n", volcal_xfyz_station_ids[volcal_xfyz_reading_station[i]],
            volcal_xfyz_reading_point[i], result.residual_mm[i] * 1e3, result.sigma_mm[i] * 1e3);
  fclose(out);

  if (!(out = open_out(dir, "volumetric.csv"))) return 2;
  if (argc == 4) {
    double *pq, *pt;
    int np = read_poses(argv[3], &pq, &pt);
    if (np < 0) return 2;
    if (write_volumetric(out, np, pq, pt, result.theta)) return 2;
    free(pq);
    free(pt);
  } else {
    /* the first reading of every distinct point, in plan order */
    static int idx[N], first[N];
    static double pq[N * NA], pt[N * 3];
    int m = 0, j;
    for (i = 0; i < N; ++i) idx[i] = i;
    qsort(idx, N, sizeof idx[0], idx_point_cmp);
    for (i = 0; i < N; ++i)
      if (i == 0 || strcmp(volcal_xfyz_reading_point[idx[i]], volcal_xfyz_reading_point[idx[i - 1]]))
        first[m++] = idx[i];
    qsort(first, m, sizeof first[0], int_cmp);
    for (j = 0; j < m; ++j) {
      for (a = 0; a < NA; ++a) pq[j * NA + a] = q[first[j] * NA + a];
      for (a = 0; a < 3; ++a) pt[j * 3 + a] = tool[first[j] * 3 + a];
    }
    if (write_volumetric(out, m, pq, pt, result.theta)) return 2;
  }
  fclose(out);

  printf("%s: %s after %d iterations; KKT residual %.3e (relative %.3e), step %.3e um, "
         "chi2/dof %.4g\n", volcal_xfyz_status_string(status),
         result.converged ? "converged" : "NOT CONVERGED", result.iterations, result.kkt,
         result.kkt_rel, result.step, result.chi2_per_dof);
  return result.converged ? 0 : 1;
}
