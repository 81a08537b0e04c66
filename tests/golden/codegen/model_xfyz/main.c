/* main.c - example program of the exported volcal model volcal_xfyz.
 *
 *   volcal_xfyz_example PARAMETERS.csv POSES.csv [OUT.csv]
 *
 * PARAMETERS.csv: name, value, unit (um, urad, mm or rad), e.g. the parameters.csv of
 * `volcal identify` or of an exported solver; parameters not listed are zero.
 * POSES.csv: one column per axis (mm / deg), optional tool_x, tool_y, tool_z (mm).
 * Writes the volumetric errors (dx_um, dy_um, dz_um: actual - nominal tool point) to OUT.csv
 * or to standard output.  Exit code 0, or 2 on bad input.
 */
#define _POSIX_C_SOURCE 200809L
#include "volcal_xfyz.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

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

int main(int argc, char **argv) {
  static char line[MAX_LINE];
  char *h[MAX_FIELDS], *f[MAX_FIELDS];
  double theta[VOLCAL_XFYZ_N_PARAMS] = {0}, *q, *tool;
  int nh, cn, cv, cu, k, row = 1, n;
  FILE *in, *out = stdout;

  if (argc < 3 || argc > 4) {
    fprintf(stderr, "usage: %s PARAMETERS.csv POSES.csv [OUT.csv]\n", argv[0]);
    return 2;
  }
  in = fopen(argv[1], "r");
  if (!in || !fgets(line, sizeof line, in)) {
    fprintf(stderr, "%s: cannot read\n", argv[1]);
    return 2;
  }
  {
    char *hdr = strdup(line[0] == '\xef' ? line + 3 : line);
    nh = split(hdr, h, MAX_FIELDS);
    cn = column(h, nh, "name", NULL);
    cv = column(h, nh, "value", NULL);
    cu = column(h, nh, "unit", NULL);
    if (cn < 0 || cv < 0 || cu < 0) {
      fprintf(stderr, "%s: the header needs name, value and unit columns\n", argv[1]);
      return 2;
    }
    while (fgets(line, sizeof line, in)) {
      int nf;
      double v, s;
      ++row;
      if (is_blank(line)) continue;
      nf = split(line, f, MAX_FIELDS);
      if (nf <= cn || nf <= cv || nf <= cu || number(f[cv], &v, 0)) {
        fprintf(stderr, "%s, row %d: bad row\n", argv[1], row);
        return 2;
      }
      for (k = 0; k < VOLCAL_XFYZ_N_PARAMS; ++k)
        if (!strcmp(volcal_xfyz_param_names[k], f[cn])) break;
      if (k == VOLCAL_XFYZ_N_PARAMS) {
        fprintf(stderr, "%s, row %d: unknown parameter '%s'\n", argv[1], row, f[cn]);
        return 2;
      }
      if (!strcmp(f[cu], "um")) s = 1e-3;
      else if (!strcmp(f[cu], "urad")) s = 1e-6;
      else if (!strcmp(f[cu], "mm") || !strcmp(f[cu], "rad")) s = 1.0;
      else {
        fprintf(stderr, "%s, row %d: unknown unit '%s'\n", argv[1], row, f[cu]);
        return 2;
      }
      if (strcmp(volcal_xfyz_param_units[k], (!strcmp(f[cu], "um") || !strcmp(f[cu], "mm"))
                                            ? "mm" : "rad")) {
        fprintf(stderr, "%s, row %d: '%s' is in %s\n", argv[1], row, f[cn],
                volcal_xfyz_param_units[k]);
        return 2;
      }
      theta[k] = v * s;
    }
    fclose(in);
    free(hdr);
  }
  n = read_poses(argv[2], &q, &tool);
  if (n < 0) return 2;
  if (argc == 4 && !(out = fopen(argv[3], "w"))) {
    fprintf(stderr, "cannot write %s\n", argv[3]);
    return 2;
  }
  if (write_volumetric(out, n, q, tool, theta)) return 2;
  if (out != stdout) fclose(out);
  free(q);
  free(tool);
  return 0;
}
