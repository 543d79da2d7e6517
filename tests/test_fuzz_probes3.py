

def test_default_names_do_not_change_when_the_10000th_pair_is_appended(tmp_path):
  """Before: the padding grew with the row count: appending the 10000th pair renamed rows
  0001..9999 to 00001..09999, so a resumed job redid all of them and kept the old outputs."""
  rows = "".join(f"a{k}.ply\tb{k}.ply\n" for k in range(1, 10001))
  before = jobs.read_pairs(_tsv(tmp_path, "source\ttarget\n" + rows.split("a10000")[0],
                                "p9999.tsv"))
  after = jobs.read_pairs(_tsv(tmp_path, "source\ttarget\n" + rows, "p10000.tsv"))
  assert [n for n, _, _ in after[:9999]] == [n for n, _, _ in before]
  assert (before[0][0], after[-1][0]) == ("0001", "10000")
