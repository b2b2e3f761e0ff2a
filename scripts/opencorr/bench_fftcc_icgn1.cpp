/*
 Benchmark harness for OpenCorr FFT-CC + ICGN (1st-order shape function), modelled on OpenCorr's
 examples/test_2d_dic_fftcc_icgn1.cpp (same calls, same order, same parameters except subset radius,
 POI list and thread count, which are set from the command line).

 usage: bench_fftcc_icgn1 REF.pgm TAR.pgm POIS.csv THREADS [REPEATS=5] [OUT.csv] [RADIUS=10]

 Timed stages (std::chrono::steady_clock, each rep starts from a fresh POI queue):
   fftcc   : new FFTCC2D(r, r, threads) + setImages + compute(poi_queue)  (the example's "FFTCC" block)
   prep    : new ICGN2D1(...) + setImages + prepare()  (gradient maps of ref + bicubic B-spline LUT of tar)
   icgn    : icgn1->compute(poi_queue)
   total   : fftcc + prep + icgn  (= the example's FFTCC + ICGN blocks; image loading excluded)
*/

#include <algorithm>
#include <chrono>
#include <cmath>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include <omp.h>

#include "oc_fftcc.h"
#include "oc_icgn.h"
#include "oc_image.h"
#include "oc_poi.h"

using namespace opencorr;
using namespace std;

static double seconds_since(chrono::steady_clock::time_point t0)
{
	return chrono::duration<double>(chrono::steady_clock::now() - t0).count();
}

static double median(vector<double> v)
{
	sort(v.begin(), v.end());
	size_t n = v.size();
	return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

int main(int argc, char** argv)
{
	if (argc < 5)
	{
		cerr << "usage: " << argv[0] << " REF.pgm TAR.pgm POIS.csv THREADS [REPEATS=5] [OUT.csv] [RADIUS=10]" << endl;
		return 1;
	}
	string ref_image_path = argv[1];
	string tar_image_path = argv[2];
	string poi_path = argv[3];
	int cpu_thread_number = atoi(argv[4]);
	int repeats = argc > 5 ? atoi(argv[5]) : 5;
	string out_path = argc > 6 ? argv[6] : "";
	int radius = argc > 7 ? atoi(argv[7]) : 10;

	Image2D ref_img(ref_image_path);
	Image2D tar_img(tar_image_path);

	//read POIs (header "x,y"; x = column, y = row)
	vector<Point2D> poi_points;
	{
		ifstream in(poi_path);
		string line;
		getline(in, line); //header
		while (getline(in, line))
		{
			if (line.empty()) continue;
			stringstream ss(line);
			string xs, ys;
			getline(ss, xs, ',');
			getline(ss, ys, ',');
			poi_points.push_back(Point2D(stoi(xs), stoi(ys)));
		}
	}

	//set OpenMP parameters (as in the example, but thread count given on the command line)
	omp_set_num_threads(cpu_thread_number);

	//set DIC parameters (example: radius 16, max_iteration 10, max_deformation_norm 0.001f)
	int subset_radius_x = radius;
	int subset_radius_y = radius;
	int max_iteration = 10;
	float max_deformation_norm = 0.001f;

	cout << "image " << ref_img.width << "x" << ref_img.height << ", POIs " << poi_points.size()
		<< ", subset " << 2 * radius + 1 << "x" << 2 * radius + 1 << ", threads " << cpu_thread_number
		<< " (omp_get_max_threads=" << omp_get_max_threads() << "), repeats " << repeats << endl;

	vector<double> t_fftcc, t_prep, t_icgn, t_total;
	vector<POI2D> poi_queue;

	for (int rep = 0; rep < repeats; rep++)
	{
		poi_queue.clear();
		for (auto& p : poi_points)
		{
			POI2D current_poi(p);
			poi_queue.push_back(current_poi);
		}

		auto t0 = chrono::steady_clock::now();

		//FFTCC
		FFTCC2D* fftcc = new FFTCC2D(subset_radius_x, subset_radius_y, cpu_thread_number);
		fftcc->setImages(ref_img, tar_img);
		fftcc->compute(poi_queue);
		double tf = seconds_since(t0);

		//ICGN with the 1st order shape function
		auto t1 = chrono::steady_clock::now();
		ICGN2D1* icgn1 = new ICGN2D1(subset_radius_x, subset_radius_y, max_deformation_norm, max_iteration, cpu_thread_number);
		icgn1->setImages(ref_img, tar_img);
		icgn1->prepare();
		double tp = seconds_since(t1);

		auto t2 = chrono::steady_clock::now();
		icgn1->compute(poi_queue);
		double ti = seconds_since(t2);

		double tt = seconds_since(t0);

		delete fftcc;
		delete icgn1;

		t_fftcc.push_back(tf);
		t_prep.push_back(tp);
		t_icgn.push_back(ti);
		t_total.push_back(tt);
		cout << fixed << setprecision(4) << "rep " << rep << ": fftcc " << tf << " s, prep(grad+bspline) " << tp
			<< " s, icgn " << ti << " s, total " << tt << " s" << endl;
	}

	double n = (double)poi_queue.size();
	double mf = median(t_fftcc), mp = median(t_prep), mi = median(t_icgn), mt = median(t_total);
	cout << fixed << setprecision(4)
		<< "MEDIAN threads=" << cpu_thread_number
		<< " fftcc=" << mf << " prep=" << mp << " icgn=" << mi << " total=" << mt
		<< setprecision(0)
		<< " POI/s(fftcc+icgn)=" << n / (mf + mi)
		<< " POI/s(total)=" << n / mt << endl;

	//result statistics for the last repetition
	int n_bad = 0, n_nonconv = 0;
	double iter_sum = 0;
	for (auto& p : poi_queue)
	{
		if (p.result.zncc < 0) n_bad++;
		if (p.result.zncc == -4.f) n_nonconv++;
		iter_sum += p.result.iteration;
	}
	cout << setprecision(3) << "flagged (zncc<0): " << n_bad << ", of which not converged (-4): " << n_nonconv
		<< ", mean iterations: " << iter_sum / n << endl;

	if (!out_path.empty())
	{
		ofstream out(out_path);
		out << "x,y,u,v,ux,uy,vx,vy,zncc,iteration,convergence,u0,v0\n";
		out << setprecision(8);
		for (auto& p : poi_queue)
		{
			out << p.x << "," << p.y << "," << p.deformation.u << "," << p.deformation.v << ","
				<< p.deformation.ux << "," << p.deformation.uy << "," << p.deformation.vx << "," << p.deformation.vy << ","
				<< p.result.zncc << "," << p.result.iteration << "," << p.result.convergence << ","
				<< p.result.u0 << "," << p.result.v0 << "\n";
		}
	}

	return 0;
}
