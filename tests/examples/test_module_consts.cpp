// Modules refuse inconsistent in-consts at init (issue 8): a task whose NDOF
// in-const does not match the DH in-const, or whose ports have another size
// than NDOF, is refused by spawn with an error naming the rmod and both sizes,
// and leaves no task behind (an error in init calls kill, the task stays
// NOT-CREATED, §3.6).
//
// The table holds two robots' out-consts: the PUMA 560's (NDOF 6, DH of
// 18 x 7 = 126) and a planar 2-link arm's (NDOF2 = 2, DH2 of 54), each from its
// own robot interface. Each module's .rmod is given NDOF from one robot and DH
// (or its vector ports) from the other with SVARALIAS.
#include "fig3_15.hpp"

#include <chimera/sbs.hpp>

#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>

namespace {

namespace fs = std::filesystem;
using chimera::sbs::Subsystem;

class ModuleConsts : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() / ("chimera_consts" + std::to_string(::getpid()));
        fs::create_directories(dir_);
        // The Figures 3.15/3.16 table plus the second robot's variables.
        std::ifstream svar(fig3_15::example_dir() + "/fig3_15.svar");
        std::string text((std::istreambuf_iterator<char>(svar)), std::istreambuf_iterator<char>());
        text.erase(text.rfind("EOF"));
        text +=
            "NAME  NDOF2\nTYPE  int\nDESC  joints of the second robot\nUNITS none\nNELEM 1\n\n"
            "NAME  DH2\nTYPE  double\nDESC  DH of the second robot\nUNITS mixed\nNELEM 54\n\n"
            "NAME  T_REF2\nTYPE  double\nDESC  torques of the second robot\nUNITS Nm\nNELEM 2\n\n"
            "NAME  Q_MEZ2\nTYPE  double\nDESC  joints of the second robot\nUNITS rad\nNELEM 2\n\n"
            "NAME  T_GRAV\nTYPE  double\nDESC  gravity torques\nUNITS Nm\nNELEM 6\n\n"
            "NAME  T_REF\nTYPE  double\nDESC  torques\nUNITS Nm\nNELEM 6\n\nEOF\n";
        write("consts.svar", text);
        write("planar2.rmod",
              "MODULE    robotsim\nDESC      second robot\n"
              "SVARALIAS NDOF=NDOF2\nSVARALIAS DH=DH2\nSVARALIAS T_REF=T_REF2\nSVARALIAS Q_MEZ=Q_MEZ2\n"
              "OUTCONST  NDOF DH\nINVAR     T_REF\nOUTVAR    Q_MEZ\nTASKTYPE  periodic\nFREQ      100\n"
              "LOCAL\nROBOT     planar2\nMODE      torque\nEOF\n");
        chimera::SbsFile file = fig3_15::load_sbs(nullptr, "consts" + std::to_string(::getpid()));
        file.svarfile = (dir_ / "consts.svar").string();
        sbs_ = Subsystem::init(file);
        fig3_15::add_module_dirs(*sbs_);
        sbs_->spawn(fig3_15::rmod("puma_position"), "robot");
        sbs_->spawn((dir_ / "planar2.rmod").string(), "robot");
    }
    void TearDown() override {
        if (sbs_) sbs_->finish();
        fs::remove_all(dir_);
    }
    void write(const std::string& name, const std::string& text) { std::ofstream(dir_ / name) << text; }

    // Spawns `rmod_text` as NAME.rmod and expects spawn to refuse it with a
    // message holding every one of `needles`; then only the two robots live.
    void expect_refused(const std::string& name, const std::string& rmod_text,
                        std::initializer_list<std::string> needles) {
        write(name + ".rmod", rmod_text);
        try {
            sbs_->spawn((dir_ / (name + ".rmod")).string(), "ctrl");
            ADD_FAILURE() << name << ": spawned with inconsistent in-consts";
        } catch (const chimera::sbs::Error& e) {
            const std::string what = e.what();
            std::printf("%s refused: %s\n", name.c_str(), what.c_str());
            for (const auto& n : needles) EXPECT_NE(what.find(n), std::string::npos) << "'" << n << "' in: " << what;
        }
        EXPECT_EQ(sbs_->status_all().size(), 2u) << name << " left a task behind";
    }

    fs::path dir_;
    std::unique_ptr<Subsystem> sbs_;
};

// NDOF 2 (the planar arm's) with the PUMA's DH of 126 elements.
constexpr const char* kMixed = "SVARALIAS NDOF=NDOF2\nINCONST   NDOF DH\n";
const std::string kDhMismatch = "in-const DH has 126 elements but NDOF 2 needs 54";

TEST_F(ModuleConsts, FwdkinRefusesDhOfAnotherNdof) {
    expect_refused("fwdkin_bad", std::string("MODULE fwdkin\nDESC x\nSVARALIAS JPOS=Q_MEZ\nSVARALIAS XPOS=X_MEZ\n") +
                                     kMixed + "INVAR JPOS\nOUTVAR XPOS\nTASKTYPE periodic\nFREQ 100\nEOF\n",
                   {"fwdkin_bad.rmod", kDhMismatch});
}

TEST_F(ModuleConsts, InvkinAndDlsikRefuseDhOfAnotherNdof) {
    expect_refused("invkin_bad", std::string("MODULE invkin\nDESC x\n") + kMixed +
                                     "INVAR X_REF\nOUTVAR Q_REF\nTASKTYPE periodic\nFREQ 100\nEOF\n",
                   {"invkin_bad.rmod", kDhMismatch});
    expect_refused("dlsik_bad", std::string("MODULE dlsik\nDESC x\n") + kMixed +
                                    "INVAR X_REF Q_REF\nOUTVAR Q^_REF\nTASKTYPE periodic\nFREQ 100\nEOF\n",
                   {"dlsik_bad.rmod", kDhMismatch});
}

TEST_F(ModuleConsts, GravcompAndInvdynRefuseDhOfAnotherNdof) {
    expect_refused("grav_bad", std::string("MODULE gravcomp\nDESC x\n") + kMixed +
                                   "INVAR Q_MEZ\nOUTVAR T_GRAV\nTASKTYPE periodic\nFREQ 100\nEOF\n",
                   {"grav_bad.rmod", kDhMismatch});
    expect_refused("invdyn_bad", std::string("MODULE invdyn\nDESC x\nSVARALIAS Q^^_U=Q^_REF\n") + kMixed +
                                     "INVAR Q_MEZ Q^_MEZ Q^^_U\nOUTVAR T_REF\nTASKTYPE periodic\nFREQ 100\nEOF\n",
                   {"invdyn_bad.rmod", kDhMismatch});
}

TEST_F(ModuleConsts, PidRefusesPortsOfAnotherSizeThanNdof) {
    // NDOF 2, joint vectors of 6: the port is named with both sizes.
    expect_refused("pid_bad",
                   "MODULE pid\nDESC x\nSVARALIAS NDOF=NDOF2\nINCONST NDOF\nINVAR Q_REF Q^_REF Q_MEZ Q^_MEZ\n"
                   "OUTVAR T_REF\nTASKTYPE periodic\nFREQ 100\nLOCAL\nKP 100\nEOF\n",
                   {"pid_bad.rmod", "has 6 elements, expected 2"});
}

TEST_F(ModuleConsts, ConsistentInConstsAreAccepted) {
    // The same fwdkin with both in-consts from the planar arm spawns: the
    // refusals above are about the mismatch, not the aliases.
    write("fwdkin_ok.rmod",
          "MODULE fwdkin\nDESC x\nSVARALIAS NDOF=NDOF2\nSVARALIAS DH=DH2\nSVARALIAS JPOS=Q_MEZ2\nSVARALIAS XPOS=X_MEZ\n"
          "INCONST NDOF DH\nINVAR JPOS\nOUTVAR XPOS\nTASKTYPE periodic\nFREQ 100\nEOF\n");
    EXPECT_NO_THROW(sbs_->spawn((dir_ / "fwdkin_ok.rmod").string(), "ctrl"));
    EXPECT_EQ(sbs_->status_all().size(), 3u);
}

}  // namespace
